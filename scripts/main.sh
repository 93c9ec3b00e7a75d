#!/usr/bin/env bash
# The README's main command: install what is missing, build, and run the embedded default
# (sim_server + coupler + device_bridge + viewer in one process over memq:// with a scripted device).
# Prints the viewer's URL (http://127.0.0.1:8080/?token=...; --viewer-port PORT, --viewer-port 0 = no viewer) and
# runs until Ctrl-C unless --duration-s is given. Arguments are passed to haptree_run (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install_deps.sh
echo "[haptree] building (log: build.log) ..."
bash scripts/build.sh > build.log 2>&1 || { tail -50 build.log; exit 1; }
exec ./build/tools/haptree_run "$@"
