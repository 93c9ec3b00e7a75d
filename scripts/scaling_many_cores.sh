#!/usr/bin/env bash
# Scaling of the adaptive step, the selection and the full DCA pass with the number of threads.
# Builds scaling_bench (Release; ccache if installed) and runs it at 1, 2, 4, 8 and 16 threads on
# chains and binary trees of 4 096 … 262 144 bodies (k = 48 and 256, 400 steps each): one CSV per
# thread count plus a merged one, and a per-thread efficiency table of the full pass on stdout.
# About 4-6 minutes on a 16-core machine.
#
#   bash scripts/scaling_many_cores.sh            # CSV to $OUT if set, else docs/data/
#   THREADS="1 2 4" SIZES=4096,16384 bash scripts/scaling_many_cores.sh
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
out=${OUT:-$root/docs/data}
build=${BUILD_DIR:-$root/build-scaling}
threads_list=${THREADS:-"1 2 4 8 16"}
sizes=${SIZES:-4096,16384,65536,262144}
ks=${KS:-48,256}
steps=${STEPS:-400}
mkdir -p "$out"
launcher=()
if command -v ccache >/dev/null; then
  launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache)
fi
echo "== configure + build scaling_bench in $build ($(nproc) CPUs)"
cmake -S "$root" -B "$build" -DCMAKE_BUILD_TYPE=Release "${launcher[@]}" > "$out/scaling_configure.log" 2>&1 ||
  { tail -20 "$out/scaling_configure.log"; exit 1; }
cmake --build "$build" -j"$(nproc)" --target scaling_bench > "$out/scaling_build.log" 2>&1 ||
  { tail -30 "$out/scaling_build.log"; exit 1; }
bench="$build/bench/scaling_bench"
uname -a > "$out/scaling_machine.txt"
(lscpu 2>/dev/null || true) >> "$out/scaling_machine.txt"
merged="$out/scaling_threads.csv"
rm -f "$merged"
for t in $threads_list; do
  csv="$out/scaling_threads_$t.csv"
  echo "== $t thread(s): load $(cut -d' ' -f1-3 /proc/loadavg)"
  # The full pass runs on t OpenMP threads (set_dca_threads); the step itself is serial, the
  # selection runs on its own worker thread.
  OMP_NUM_THREADS=$t OMP_PROC_BIND=false "$bench" --sizes "$sizes" --k "$ks" --steps "$steps" --threads "$t" \
    --full-reps 5 --csv "$csv"
  if [ ! -f "$merged" ]; then cp "$csv" "$merged"; else tail -n +2 "$csv" >> "$merged"; fi
done
echo "== full pass: speed-up and efficiency per thread count (from $merged)"
python3 - "$merged" <<'PY'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
base = {}
for r in rows:
    if r["threads"] == "1": base[(r["shape"], r["n"], r["k"])] = float(r["full_pass_us"])
print("| shape | n | threads | full pass us | speed-up | efficiency | median step us | worst step us |")
print("|---|---|---|---|---|---|---|---|")
seen = set()
for r in rows:
    key = (r["shape"], r["n"], r["threads"])
    if key in seen: continue
    seen.add(key)
    b = base.get((r["shape"], r["n"], r["k"]))
    full, t = float(r["full_pass_us"]), int(r["threads"])
    sp = b / full if b else float("nan")
    print(f"| {r['shape']} | {r['n']} | {t} | {full:.0f} | {sp:.2f} | {sp / t:.2f} | {float(r['median_us']):.1f} | {float(r['worst_us']):.1f} |")
PY
echo "CSV: $merged (one file per thread count beside it); machine: $out/scaling_machine.txt"
