#!/usr/bin/env bash
# The README's test command: install what is missing, configure, build, run every test.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install_deps.sh --tests
# HAPTREE_PACKAGE: shared libraries and man pages too, so that install_package (label install) can
# install the tree, build a program against it and build the .debs (docs/install.md).
bash scripts/build.sh -DHAPTREE_BUILD_TESTS=ON -DHAPTREE_BUILD_BENCH=ON -DHAPTREE_BUILD_PYTHON=ON \
                      -DHAPTREE_BUILD_JAVA=ON -DHAPTREE_PACKAGE=ON
# install_package (label install) also installs the .debs with dpkg -i and removes them, as root.
if [ "$(id -u)" -eq 0 ]; then
  export HAPTREE_TEST_DPKG_INSTALL=${HAPTREE_TEST_DPKG_INSTALL:-1}
fi
cd build
ctest --output-on-failure -j "${HAPTREE_JOBS:-$(nproc)}" --timeout 900
cd ..
# libFuzzer smoke runs (CTest label `fuzz`, 20 s per target) in their own clang tree (docs/fuzzing.md).
bash scripts/fuzz.sh smoke
