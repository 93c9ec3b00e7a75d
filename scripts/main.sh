#!/usr/bin/env bash
# The README's main command: install what is missing, build, and run the embedded default
# (sim_server + coupler + device_bridge + viewer in one process over memq:// with a scripted device).
# Prints the viewer's URL (http://127.0.0.1:8080/?token=...; --viewer-port PORT, --viewer-port 0 = no viewer) and
# runs until Ctrl-C unless --duration-s is given. Arguments are passed to haptree_run (try --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install_deps.sh   # build and run only; scripts/test.sh adds what the tests need
# A fresh build directory gets the lean configuration (no tests, benchmarks, Python module or Java
# jar: their packages are not installed); an existing one keeps its options.
lean=()
[ -f build/CMakeCache.txt ] || lean=(-DHAPTREE_BUILD_TESTS=OFF -DHAPTREE_BUILD_BENCH=OFF
                                     -DHAPTREE_BUILD_PYTHON=OFF -DHAPTREE_BUILD_JAVA=OFF)
echo "[haptree] building (log: build.log) ..."
bash scripts/build.sh "${lean[@]}" > build.log 2>&1 || { tail -50 build.log; exit 1; }
exec ./build/launcher/haptree_run "$@"
