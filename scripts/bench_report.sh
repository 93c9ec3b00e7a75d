#!/usr/bin/env bash
# Runs the benchmark programs, writes their CSV under docs/data/ and rewrites the tables of
# docs/performance.md between its marker comments (<!-- bench:ID begin --> … <!-- bench:ID end -->),
# each with the machine and the exact command beside it. Re-running it is how the page is updated.
#
#   scripts/bench_report.sh [options] [SECTION...]
#     SECTION      dca dcathreads adaptive coupler forcefield bus scaling threads latency viewer
#                  (default: all but latency and viewer)
#     --build DIR  build folder with the benchmark programs (default build; configure with
#                  -DHAPTREE_BUILD_BENCH=ON, then: cmake --build DIR --target bench_peers dca_bench
#                  adaptive_sweep coupling_bench molecule_bench bus_bench scaling_bench stress_report)
#     --data DIR   where the CSV go (default docs/data)
#     --page FILE  the page to rewrite (default docs/performance.md)
#     --quick      tiny sizes and durations (under a minute in all): checks the script, not the
#                  machine; without --page/--data it writes into a new temporary folder
#     --dry-run    print the commands; run nothing, change nothing
#
# Sections and what they run (full sizes; --quick shrinks each):
#   dca        bench_peers: full DCA (default and one plain pass), the adaptive pass, Bullet, Simbody,
#              MuJoCo (the peers compiled in) on chains, binary trees, the protein-like tree and
#              bacteriorhodopsin of 1 024 and 4 096 bodies                                    (~9 min)
#   dcathreads dca_bench: one DCA pass on one and on two threads (1 024 bodies, protein-like)   (~40 s)
#   adaptive   adaptive_sweep: step time against error, budgets and thresholds                  (~35 s)
#   coupler    coupling_bench: the O(log n) coupler against n, 1 grab                            (~20 s)
#   forcefield molecule_bench: bacteriorhodopsin, force field and whole step                      (~10 s)
#   bus        bus_bench: the transports alone, a ping-pong of real messages (udpm as root)      (~10 s)
#   scaling    scaling_bench: the adaptive step against n (1 024 … 65 536 bodies)                (~2 min)
#   threads    no run: renders docs/data/scaling_16_threads/ (scripts/scaling_many_cores.sh with
#              OUT=docs/data/scaling_16_threads on a many-core machine re-measures it)
#   latency    scripts/measure_latency.sh (root, stress-ng, rt-tests; only when named)       (~6 min)
#   viewer     tests/browser/viewer_cost.py: the session without viewer, with it, with a headless
#              chromium tab (chromium; only when named)                                       (~1 min)
# A program that is not built is said and its block left as it is (exit status 1 at the end).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=build data= page= quick=0 dry=0
sections=()
while [ $# -gt 0 ]; do
  case $1 in
    --build) build=$2; shift 2 ;;
    --data) data=$2; shift 2 ;;
    --page) page=$2; shift 2 ;;
    --quick) quick=1; shift ;;
    --dry-run) dry=1; shift ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    -*) echo "bench_report: unknown option $1 (see --help)" >&2; exit 2 ;;
    *) sections+=("$1"); shift ;;
  esac
done
[ ${#sections[@]} -gt 0 ] || sections=(dca dcathreads adaptive coupler forcefield bus scaling threads)
cd "$root"
tables="python3 $root/scripts/bench_tables.py"
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# A quick run checks the script: unless told otherwise it leaves the committed page and data alone.
if [ $quick -eq 1 ] && [ -z "$page$data" ] && [ $dry -eq 0 ]; then
  scratch=$(mktemp -d)
  page=$scratch/performance.md data=$scratch/data
  cp docs/performance.md "$page"
  echo "bench_report: --quick writes into $scratch (give --page/--data to choose)"
fi
page=${page:-docs/performance.md} data=${data:-docs/data}
[ -f "$page" ] || { echo "bench_report: $page: no such file" >&2; exit 2; }
mkdir -p "$data"
missing=0

# The machine, as the programs see it: CPU model and cores from the kernel, the ISA level of the
# build and the kernel level chosen at run time from stress_report's own report when it is built.
cpu=$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1)
machine="$cpu, $(nproc) cores, $(uname -sr)"
if [ -x "$build/tools/stress_report" ]; then
  isa=$("$build/tools/stress_report" --sections isa 2>/dev/null |
        sed -n 's/^| ISA level (CMake) | \(.*\) |$/build \1/p; s/^| run-time kernel level[^|]*| \(.*\) |$/kernel level \1/p' |
        paste -sd ';' | sed 's/;/; /g')
  [ -z "$isa" ] || machine="$machine; $isa"
fi
echo "machine: $machine"

# run ID PROGRAM ARGS...: the command line, as a user types it from the repository root
have() { [ -x "$build/$1" ] || { echo "bench_report: $build/$1 is not built; block '$2' left as it is" >&2; missing=1; return 1; }; }
run() {
  local id=$1; shift
  echo "== $id: $*"
  [ $dry -eq 1 ] && return 0
  "$@" > "$tmp/$id.out" 2> "$tmp/$id.err" || { cat "$tmp/$id.err" >&2; echo "bench_report: $id failed" >&2; exit 1; }
}
# block ID COMMAND-TEXT: the machine and command lines, then the table in $tmp/ID.md, into the page
block() {
  local id=$1 cmd=$2
  [ $dry -eq 1 ] && return 0
  { echo "machine: $machine, load average $(cut -d' ' -f1 /proc/loadavg) at the start  "
    echo "command: \`$cmd\`"
    [ $quick -eq 0 ] || echo "(a \`--quick\` run: tiny sizes, a check of the script, not figures to quote)"
    echo
    cat "$tmp/$id.md"; } > "$tmp/$id.block"
  $tables splice "$page" "$id" "$tmp/$id.block"
  echo "   -> $page, block bench:$id"
}

for s in "${sections[@]}"; do
  case $s in
    dca)
      have bench/bench_peers dca || continue
      if [ $quick -eq 1 ]; then args=(--models chain protein_like --sizes 64 --engines haptree haptree_plain
        haptree_adaptive bullet simbody mujoco --budgets 16 --min-seconds 0.02 --max-reps 50)
      else args=(--models chain binary_tree protein_like bacteriorhodopsin --sizes 1024 4096 --engines haptree
        haptree_plain haptree_adaptive bullet simbody mujoco --budgets 48 --min-seconds 1); fi
      run dca "$build/bench/bench_peers" "${args[@]}" --csv "$data/peers.csv"
      [ $dry -eq 1 ] || $tables peers "$data/peers.csv" > "$tmp/dca.md"
      block dca "$build/bench/bench_peers ${args[*]} --csv $data/peers.csv" ;;
    dcathreads)
      have bench/dca_bench dcathreads || continue
      if [ $quick -eq 1 ]; then args=("--benchmark_filter=BM_(Chain|BinaryTree)(2T)?/16(/|\$)"
        --benchmark_min_time=0.01 --benchmark_repetitions=2)
      else args=("--benchmark_filter=BM_(Chain|BinaryTree)(2T)?/1024(/|\$)|BM_ProteinLike(2T)?(/|\$)"
        --benchmark_min_time=1 --benchmark_repetitions=3); fi
      run dcathreads "$build/bench/dca_bench" "${args[@]}" --benchmark_format=csv
      if [ $dry -eq 0 ]; then
        cp "$tmp/dcathreads.out" "$data/dca_bench.csv"
        $tables gbench "$data/dca_bench.csv" > "$tmp/dcathreads.md"
      fi
      block dcathreads "$build/bench/dca_bench '${args[0]}' ${args[*]:1} --benchmark_format=csv" ;;
    bus)
      have bench/bus_bench bus || continue
      if [ $quick -eq 1 ]; then args=(--transport memq --round-trips 200 --warmup 50)
      else args=(--transport shm-thread --transport shm-process --transport memq --round-trips 20000)
        [ "$(id -u)" -ne 0 ] || args+=(--transport udpm); fi
      run bus "$build/bench/bus_bench" "${args[@]}"
      if [ $dry -eq 0 ]; then
        $tables md2csv < "$tmp/bus.out" > "$data/bus.csv"
        grep '^|' "$tmp/bus.out" > "$tmp/bus.md"
      fi
      block bus "$build/bench/bus_bench ${args[*]}" ;;
    adaptive)
      have tools/adaptive_sweep adaptive || continue
      if [ $quick -eq 1 ]; then args=(--scenes protein_like,ala20 --budgets 16,48 --eps-rel 1e-4 --robot-steps 20
        --mol-steps 10 --warmup 0 --gravity-z 0)
      else args=(--scenes protein_like,chain4096,binary_tree4095,bacteriorhodopsin,ala20 --budgets 8,16,32,48,96,192,all
        --eps-rel 1e-2,1e-4,1e-6 --robot-steps 1000 --mol-steps 200 --warmup 0 --gravity-z 0); fi
      run adaptive "$build/tools/adaptive_sweep" "${args[@]}" --csv "$data/adaptive_sweep.csv"
      [ $dry -eq 1 ] || $tables adaptive "$data/adaptive_sweep.csv" > "$tmp/adaptive.md"
      block adaptive "$build/tools/adaptive_sweep ${args[*]} --csv $data/adaptive_sweep.csv"
      if [ $dry -eq 0 ] && [ $quick -eq 0 ]; then
        if python3 -c 'import matplotlib' 2>/dev/null; then
          python3 tools/plot_adaptive.py "$data/adaptive_sweep.csv" --out-dir docs/img
        else echo "bench_report: matplotlib not installed, the plots in docs/img were not redrawn" >&2; fi
      fi ;;
    coupler)
      have bench/coupling_bench coupler || continue
      if [ $quick -eq 1 ]; then args=(--calls 100 --sets 2 --min-log2 4 --max-log2 8 --nf 1 2)
      else args=(--min-log2 10 --max-log2 16 --nf 1 4); fi
      run coupler "$build/bench/coupling_bench" "${args[@]}"
      if [ $dry -eq 0 ]; then
        $tables md2csv < "$tmp/coupler.out" > "$data/coupling.csv"
        { grep '^|' "$tmp/coupler.out"; echo; grep -v '^|' "$tmp/coupler.out" | sed '/^$/d; s/$/  /'; } > "$tmp/coupler.md"
      fi
      block coupler "$build/bench/coupling_bench ${args[*]}" ;;
    forcefield)
      have bench/molecule_bench forcefield || continue
      if [ $quick -eq 1 ]; then args=(--scenes ala20 --steps 10)
      else args=(--scenes bacteriorhodopsin --steps 200); fi
      run forcefield "$build/bench/molecule_bench" "${args[@]}"
      if [ $dry -eq 0 ]; then
        $tables md2csv < "$tmp/forcefield.out" > "$data/molecule.csv"
        grep '^|' "$tmp/forcefield.out" > "$tmp/forcefield.md"
      fi
      block forcefield "$build/bench/molecule_bench ${args[*]}" ;;
    scaling)
      have bench/scaling_bench scaling || continue
      if [ $quick -eq 1 ]; then args=(--shapes chain --sizes 1024 --k 16 --steps 20 --full-reps 1)
      else args=(--sizes 1024,4096,16384,65536 --k 48,256 --steps 2000); fi
      run scaling "$build/bench/scaling_bench" "${args[@]}" --csv "$data/scaling.csv"
      [ $dry -eq 1 ] || $tables scaling "$data/scaling.csv" > "$tmp/scaling.md"
      block scaling "$build/bench/scaling_bench ${args[*]} --csv $data/scaling.csv" ;;
    threads)
      src=docs/data/scaling_16_threads
      echo "== threads: rendered from $src (recorded on the machine in $src/scaling_machine.txt)"
      [ $dry -eq 1 ] && continue
      $tables threads "$src" > "$tmp/threads.md"
      tm=$(sed -n 's/^Model name:[[:space:]]*//p' "$src/scaling_machine.txt" | head -1)
      tc=$(sed -n 's/^CPU(s):[[:space:]]*//p' "$src/scaling_machine.txt" | head -1)
      { echo "machine: $tm, $tc cores (KVM), idle ($src/scaling_machine.txt)  "
        echo "command: \`OMP_NUM_THREADS=T build/bench/scaling_bench --sizes 65536,262144 --k 48,256 --steps 200 --threads T --full-reps 5 --csv $src/scaling_threads_T.csv\` for T = 1, 2, 4, 8, 16"
        echo; cat "$tmp/threads.md"; } > "$tmp/threads.block"
      $tables splice "$page" threads "$tmp/threads.block"
      echo "   -> $page, block bench:threads" ;;
    latency)
      [ "$(id -u)" -eq 0 ] || { echo "bench_report: latency needs root (network namespace, SCHED_FIFO)" >&2; missing=1; continue; }
      have coupler/coupler latency || continue
      dur=8; [ $quick -eq 0 ] || dur=1
      filter=.; [ $quick -eq 0 ] || filter='^shm/none/fifo-busypoll$'
      run latency bash scripts/measure_latency.sh "$build" $dur "$data/latency.csv" "$filter"
      [ $dry -eq 1 ] || $tables latency "$data/latency.csv" > "$tmp/latency.md"
      block latency "scripts/measure_latency.sh $build $dur $data/latency.csv '$filter'" ;;
    viewer)
      command -v chromium >/dev/null || { echo "bench_report: viewer needs Debian's chromium" >&2; missing=1; continue; }
      have launcher/haptree_run viewer || continue
      secs=20; [ $quick -eq 0 ] || secs=3
      run viewer /usr/bin/python3 tests/browser/viewer_cost.py "$build/launcher/haptree_run" $secs
      if [ $dry -eq 0 ]; then
        $tables md2csv < "$tmp/viewer.out" > "$data/viewer_cost.csv"
        grep '^|' "$tmp/viewer.out" > "$tmp/viewer.md"
      fi
      block viewer "/usr/bin/python3 tests/browser/viewer_cost.py $build/launcher/haptree_run $secs" ;;
    *) echo "bench_report: unknown section '$s' (see --help)" >&2; exit 2 ;;
  esac
done
exit $missing
