#!/usr/bin/env bash
# Configures and builds haptree in ./build (Release). Extra args go to cmake configure.
set -euo pipefail
cd "$(dirname "$0")/.."
JOBS=${HAPTREE_JOBS:-$(nproc)}
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release "$@" > build.configure.log 2>&1 || { cat build.configure.log; exit 1; }
cmake --build build -j "$JOBS"
