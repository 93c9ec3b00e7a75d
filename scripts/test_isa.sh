#!/usr/bin/env bash
# Builds and runs the test suite at three x86-64 ISA levels, each in its own build directory:
#   generic  build-generic  the default options         (x86-64-v2: SSE4.2, no FMA; the vectorised
#                                                         kernels chosen at run time from the CPU)
#   v3       build-v3       -DHAPTREE_MARCH=x86-64-v3   (AVX2 + FMA everywhere)
#   native   build-native   -DHAPTREE_NATIVE=ON         (-march=native of this machine)
# Floating-point results differ between them (vector width, FMA contraction), so a tolerance that
# holds on only one of them is caught here. The run-time kernels are compared level against level
# by isa_kernel_test (HAPTREE_ISA=generic|avx2|avx512 caps them for a whole run). ccache is used
# when installed.
#
# Usage: bash scripts/test_isa.sh [--configs "generic v3 native"] [--label-regex REGEX]
#                                 [--targets "T1 T2 ..."] [--numerics] [--build-only] [--jobs N]
#                                 [--report "SECTIONS"]
#   --label-regex  run only tests whose CTest labels match (e.g. "unit|oracle|stress")
#   --targets      build only these targets (default: everything)
#   --numerics     the numerical suite only: labels "unit|oracle|stress", building every test program
#                  labelled oracle or stress and every tests/core program, found from the configured
#                  tree (so tests added later are not silently left out); a fraction of the full build
#   --report       also build tools/stress_report and run these sections of it (e.g. "isa light ratio
#                  coaxial welds far") in each configuration: build-<c>/stress_report.md
# Prints one line per configuration and exits non-zero if any configuration failed.
set -euo pipefail
cd "$(dirname "$0")/.."
configs="generic v3 native"
labels=""
build_only=0
targets=""
numerics=0
report=""
jobs=${HAPTREE_JOBS:-$(nproc)}
while [ $# -gt 0 ]; do
  case "$1" in
    --configs) configs="$2"; shift 2 ;;
    --label-regex) labels="$2"; shift 2 ;;
    --build-only) build_only=1; shift ;;
    --targets) targets="$2"; shift 2 ;;
    --numerics) numerics=1; labels="unit|oracle|stress"; shift ;;
    --jobs) jobs="$2"; shift 2 ;;
    --report) report="$2"; shift 2 ;;
    -h|--help) sed -n '2,21p' "$0"; exit 0 ;;
    *) echo "test_isa.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
done
launcher=()
if command -v ccache > /dev/null; then launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache); fi
summary=()
status=0
for c in $configs; do
  case "$c" in
    generic) flags=(-DHAPTREE_NATIVE=OFF -DHAPTREE_MARCH=) ;;
    v3) flags=(-DHAPTREE_MARCH=x86-64-v3) ;;
    native) flags=(-DHAPTREE_NATIVE=ON -DHAPTREE_MARCH=) ;;
    *) echo "test_isa.sh: unknown configuration '$c' (generic, v3, native)" >&2; exit 2 ;;
  esac
  dir="build-$c"
  echo "== $c: configure and build in $dir"
  mkdir -p "$dir"
  cmake -S . -B "$dir" -DCMAKE_BUILD_TYPE=Release "${launcher[@]}" "${flags[@]}" \
    > "$dir/test_isa.configure.log" 2>&1 || { cat "$dir/test_isa.configure.log"; exit 1; }
  tgt=()
  sel="$targets"
  if [ "$numerics" = 1 ] && [ -z "$targets" ]; then
    # haptree_add_test writes <target>_labels.cmake with the target's labels (tests/CMakeLists.txt).
    # A label-matched test whose program is not built is silently skipped by ctest -L, so build all.
    sel=$(for f in $(find "$dir/tests" -name '*_labels.cmake' | sort); do
            n=$(basename "$f" _labels.cmake)
            if grep -qE 'LABELS "[^"]*(oracle|stress)' "$f" || [[ "$f" == "$dir/tests/core/"* ]]; then
              echo "$n"; fi; done)
    [ -n "$sel" ] || { echo "test_isa.sh: no numeric test targets found in $dir/tests" >&2; exit 1; }
    echo "== $c: targets $(echo $sel)"
  fi
  for x in $sel; do tgt+=(--target "$x"); done
  [ -n "$report" ] && [ ${#tgt[@]} -gt 0 ] && tgt+=(--target stress_report)
  if ! cmake --build "$dir" -j "$jobs" "${tgt[@]}" > "$dir/test_isa.build.log" 2>&1; then
    tail -30 "$dir/test_isa.build.log"
    summary+=("$c: BUILD FAILED (see $dir/test_isa.build.log)")
    status=1
    continue
  fi
  [ "$build_only" = 1 ] && { summary+=("$c: built"); continue; }
  args=(--output-on-failure -j "$jobs" --timeout 900)
  [ -n "$labels" ] && args+=(-L "$labels")
  echo "== $c: ctest ${labels:+-L \"$labels\"}"
  if (cd "$dir" && ctest "${args[@]}") > "$dir/test_isa.ctest.log" 2>&1; then r=ok; else r=FAILED; status=1; fi
  line=$(grep -E "tests passed|tests failed" "$dir/test_isa.ctest.log" | tail -1)
  march=$(grep -o -- '-march=[^ ]*' "$dir/compile_commands.json" | head -1)
  summary+=("$c (${march:-no -march}): $r: $line")
  [ "$r" = FAILED ] && grep -E "\(Failed\)|\(Timeout\)|\*\*\*" "$dir/test_isa.ctest.log" | head -20 || true
  if [ -n "$report" ]; then
    echo "== $c: stress_report --sections $report"
    # shellcheck disable=SC2086  # the section list is split on purpose
    if "$dir/tools/stress_report" --sections $report > "$dir/stress_report.md" 2> "$dir/stress_report.log"; then
      summary+=("$c: stress_report written to $dir/stress_report.md")
    else
      summary+=("$c: stress_report FAILED (see $dir/stress_report.log)"); status=1
    fi
  fi
done
echo "== summary"
printf '%s\n' "${summary[@]}"
exit $status
