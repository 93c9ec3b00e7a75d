#!/usr/bin/env bash
# The test docs_bench_report: scripts/bench_report.sh --quick against BUILD_DIR, into a copy of
# docs/performance.md in a temporary folder. Passes when every section whose program is built
# rewrote its block (the quick run's note, a table row with a number) and the committed page and
# docs/data are untouched.
#   scripts/check_bench_report.sh BUILD_DIR
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=$(cd "${1:?usage: check_bench_report.sh BUILD_DIR}" && pwd)
cd "$root"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
cp docs/performance.md "$tmp/performance.md"
before=$(cat docs/performance.md docs/data/*.csv | sha256sum)

declare -A program=([dca]=bench/bench_peers [dcathreads]=bench/dca_bench [adaptive]=tools/adaptive_sweep
                    [coupler]=bench/coupling_bench [forcefield]=bench/molecule_bench [bus]=bench/bus_bench
                    [scaling]=bench/scaling_bench)
sections=()
for s in dca dcathreads adaptive coupler forcefield bus scaling; do
  if [ -x "$build/${program[$s]}" ]; then sections+=("$s"); else echo "not built: ${program[$s]} (block $s not checked)"; fi
done
[ -x "$build/bench/coupling_bench" ] || { echo "FAIL: coupling_bench is not built in $build" >&2; exit 1; }
sections+=(threads)

bash scripts/bench_report.sh --quick --build "$build" --data "$tmp/data" --page "$tmp/performance.md" "${sections[@]}"

status=0
for s in "${sections[@]}"; do
  block=$(sed -n "/<!-- bench:$s begin -->/,/<!-- bench:$s end -->/p" "$tmp/performance.md")
  if [ "$s" != threads ] && ! grep -q 'a `--quick` run' <<<"$block"; then
    echo "FAIL: block $s was not rewritten" >&2; status=1
  fi
  grep -q '^command: `' <<<"$block" || { echo "FAIL: block $s has no command line" >&2; status=1; }
  grep -q '^machine: ' <<<"$block" || { echo "FAIL: block $s has no machine line" >&2; status=1; }
  grep -qE '^\| [^|]+ \|.*[0-9]' <<<"$block" || { echo "FAIL: block $s has no table row with a number" >&2; status=1; }
done
declare -A csv_of=([dca]=peers.csv [dcathreads]=dca_bench.csv [adaptive]=adaptive_sweep.csv
                   [coupler]=coupling.csv [forcefield]=molecule.csv [bus]=bus.csv [scaling]=scaling.csv)
for s in "${sections[@]}"; do
  [ "$s" = threads ] && continue
  [ -s "$tmp/data/${csv_of[$s]}" ] || { echo "FAIL: block $s wrote no ${csv_of[$s]}" >&2; status=1; }
done
after=$(cat docs/performance.md docs/data/*.csv | sha256sum)
[ "$before" = "$after" ] || { echo "FAIL: the committed page or docs/data changed" >&2; status=1; }
[ $status -ne 0 ] || echo "check_bench_report: ${#sections[@]} block(s) regenerated (${sections[*]})"
exit $status
