#!/usr/bin/env bash
# Whole pulled sessions of the launcher at scale: for each scene and DOF budget, `haptree_run` (one process,
# sim_server + coupler + scripted device in threads over memq://, the defaults otherwise: 1 000 steps/s, a
# 10 kHz coupler, 50 ms watchdog) runs DURATION_S seconds while the scripted user grabs the last body at
# 0.7 s and holds the pull until 3 s before the end. Nothing leaves the process. Prints a table and writes
# a CSV: sim steps per second (the slowest whole second and the median), the longest whole step after the
# first (selection, snapshot and scene chunks included), the oldest snapshot age at any 1-s status tick,
# the oldest input the coupler's watchdog saw while pulling, the slowest coupler second, watchdog trips
# while pulling (each one takes the user's force away), blow-up resets, and the peak resident memory.
#   scripts/launcher_sessions.sh [BUILD_DIR] [DURATION_S] [CSV]
#   SCENES="chain:65536 binary_tree:65535" BUDGETS="48 256" scripts/launcher_sessions.sh build 60 out.csv
set -euo pipefail
build=$(realpath "${1:-build}")
duration=${2:-60}
csv=${3:-launcher_sessions.csv}
read -r -a scenes <<<"${SCENES:-chain:65536 binary_tree:65535}"
read -r -a budgets <<<"${BUDGETS:-48 256}"
run="$build/launcher/haptree_run"
[ -x "$run" ] || { echo "launcher_sessions: no $run (build the haptree_run target)" >&2; exit 2; }
work=$(mktemp -d /tmp/launcher_sessions.XXXXXX)
trap 'rm -rf "$work"' EXIT
echo "scene,n,k,duration_s,steps,steps_per_s_min,steps_per_s_median,longest_step_ms,tick_snapshot_age_max_ms,pull_input_age_max_ms,coupler_hz_min,trips_while_pulling,resets,rss_mb,load1" >"$csv"
for sn in "${scenes[@]}"; do
  scene=${sn%%:*}
  n=${sn##*:}
  for k in "${budgets[@]}"; do
    echo "== $scene $n, k = $k, $duration s ..." >&2
    /usr/bin/time -f "rss_kb %M" "$run" --scene "$scene" --n "$n" --budget-dofs "$k" --duration-s "$duration" \
      --viewer-port 0 --json >"$work/status.json" 2>"$work/log.txt" || {
      echo "launcher_sessions: haptree_run failed; its log:" >&2
      tail -20 "$work/log.txt" >&2
      exit 1
    }
    python3 - "$work/status.json" "$work/log.txt" "$scene" "$n" "$k" "$duration" "$(cut -d' ' -f1 /proc/loadavg)" \
      >>"$csv" <<'EOF'
import json, re, statistics, sys
status, log, scene, n, k, duration, load = sys.argv[1:]
steps, ages, rates, prev = [], [], [], None
for line in open(status):
    o = json.loads(line)
    s, u = o["sim"], o["users"][0]
    if prev is not None:
        steps.append(s["steps"] - prev)
    prev = s["steps"]
    if u["snapshot_age_ms"] is not None:
        ages.append(u["snapshot_age_ms"])
    if u["rate_hz"]:
        rates.append(u["rate_hz"])
text = open(log).read()
def grab(pattern):
    m = re.search(pattern, text)
    return m.group(1) if m else "nan"
print(",".join(str(x) for x in [
    scene, n, k, duration, grab(r"summary: (\d+) sim steps"),
    min(steps[1:]) if len(steps) > 1 else "nan",       # the first second holds the first selection
    statistics.median(steps) if steps else "nan",
    grab(r"longest step after the first ([0-9.]+) ms"),
    f"{max(ages):.2f}" if ages else "nan",
    grab(r"oldest input while pulling ([0-9.]+) ms"),
    f"{min(rates):.0f}" if rates else "nan",
    grab(r"\((\d+) while pulling\)"),
    grab(r"(\d+) blow-up resets"),
    round(int(grab(r"rss_kb (\d+)")) / 1024),
    load]))
EOF
  done
done
python3 - "$csv" <<'EOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
cols = [("scene", "scene"), ("n", "n"), ("k", "k"), ("steps/s, slowest second", "steps_per_s_min"),
        ("steps/s, median second", "steps_per_s_median"), ("longest step ms", "longest_step_ms"),
        ("snapshot age at ticks, max ms", "tick_snapshot_age_max_ms"),
        ("oldest input while pulling ms", "pull_input_age_max_ms"), ("coupler Hz, slowest second", "coupler_hz_min"),
        ("watchdog trips while pulling", "trips_while_pulling"), ("blow-up resets", "resets"),
        ("RSS MB", "rss_mb"), ("load average", "load1")]
print("| " + " | ".join(c[0] for c in cols) + " |")
print("|" + "---|" * len(cols))
for r in rows:
    print("| " + " | ".join(str(r[c[1]]).replace("_", " ") for c in cols) + " |")
EOF
