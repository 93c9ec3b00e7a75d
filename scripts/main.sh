#!/usr/bin/env bash
# The README's main command: install what is missing, build, and run the embedded default
# (sim_server + coupler + device_bridge on this host with a simulated device).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install_deps.sh
bash scripts/build.sh > build.log 2>&1 || { tail -50 build.log; exit 1; }
exec ./build/tools/haptree_run "$@"
