#!/usr/bin/env bash
# libFuzzer targets of fuzz/ (docs/fuzzing.md) in their own clang tree, build-fuzz/:
#   bash scripts/fuzz.sh build                    configure (clang-14, HAPTREE_FUZZ=ON) and build the targets
#   bash scripts/fuzz.sh smoke                    build, then the 20-s CTest smoke run of every target (label fuzz)
#   bash scripts/fuzz.sh run TARGET [SECONDS] [libFuzzer args...]
#                                                 a long run (default 600 s) into build-fuzz/runs/TARGET/
#                                                 (corpus/, crash-* artifacts, log); TARGET e.g. urdf
#   bash scripts/fuzz.sh seeds                    rewrite the generated LCM seeds in fuzz/corpus/
#   bash scripts/fuzz.sh list                     the target names
# A crash found by `run` goes into fuzz/regressions/TARGET/ once fixed: the gcc tree replays it (CTest
# fuzz_replay_TARGET). Environment: HAPTREE_JOBS (build parallelism, default 2), FUZZ_BUILD_DIR.
set -euo pipefail
cd "$(dirname "$0")/.."
B=${FUZZ_BUILD_DIR:-build-fuzz}
J=${HAPTREE_JOBS:-2}

build() {
  command -v clang++-14 >/dev/null || { echo "clang++-14 missing: bash scripts/install_deps.sh" >&2; exit 1; }
  if [ ! -f "$B/CMakeCache.txt" ]; then
    local launcher=()
    command -v ccache >/dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
    CC=clang-14 CXX=clang++-14 cmake -S . -B "$B" -DHAPTREE_FUZZ=ON -DHAPTREE_BUILD_TESTS=OFF \
      -DHAPTREE_BUILD_BENCH=OFF -DCMAKE_BUILD_TYPE=RelWithDebInfo \
      -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g" "${launcher[@]}" >/dev/null
  fi
  cmake --build "$B" -j "$J" --target haptree_fuzzers
}

targets() { sed -n 's/^haptree_add_fuzzer(\([a-z_0-9]*\) .*/\1/p' fuzz/CMakeLists.txt; }

case "${1:-}" in
  build) build ;;
  smoke)
    build
    ctest --test-dir "$B" -L fuzz --output-on-failure -j "$J" ;;
  run)
    t=${2:?target name (bash scripts/fuzz.sh list)}
    secs=${3:-600}
    shift $(( $# >= 3 ? 3 : 2 ))
    build
    w=$B/runs/$t
    mkdir -p "$w/corpus"
    "$B/fuzz/fuzz_make_seeds" "$B/fuzz/seeds" >/dev/null
    dirs=()
    for d in fuzz/corpus/$t fuzz/regressions/$t $B/fuzz/seeds/$t; do [ -d "$d" ] && dirs+=("$d"); done
    echo "[fuzz] $t for $secs s; log: $w/log"
    "$B/fuzz/fuzz_$t" -max_total_time="$secs" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
      -artifact_prefix="$w/" "$@" "$w/corpus" "${dirs[@]}" >"$w/log" 2>&1 || {
        echo "[fuzz] $t stopped with a finding: see $w/log and $w/crash-*" >&2; exit 1; }
    tail -n 20 "$w/log" ;;
  seeds)
    build
    "$B/fuzz/fuzz_make_seeds" fuzz/corpus ;;
  list) targets ;;
  *) sed -n '2,12p' "$0"; exit 2 ;;
esac
