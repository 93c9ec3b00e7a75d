#!/usr/bin/env bash
# Short run of scripts/launcher_sessions.sh (a 256-link chain, 3 s): the script runs haptree_run, reads its
# status lines and summary, and writes one CSV row whose figures are all numbers: steps done, the whole
# seconds' rates, the longest step, the oldest input while pulling (present only if the grab's snapshots
# were in use), the trip and reset counts and the peak memory.
set -euo pipefail
build=$1
src=$(cd "$(dirname "$0")/../.." && pwd)
out=$(mktemp -d /tmp/launcher_sessions_smoke.XXXXXX)
trap 'rm -rf "$out"' EXIT
SCENES="chain:256" BUDGETS="16" bash "$src/scripts/launcher_sessions.sh" "$build" 3 "$out/s.csv" >"$out/table.md"
cat "$out/table.md"
python3 - "$out/s.csv" <<'PY'
import csv, math, sys
rows = list(csv.DictReader(open(sys.argv[1])))
assert len(rows) == 1, rows
r = rows[0]
assert (r["scene"], r["n"], r["k"]) == ("chain", "256", "16"), r
for key in ("steps", "steps_per_s_min", "steps_per_s_median", "longest_step_ms", "tick_snapshot_age_max_ms",
            "pull_input_age_max_ms", "coupler_hz_min", "trips_while_pulling", "resets", "rss_mb"):
    v = float(r[key])
    assert math.isfinite(v) and v >= 0, (key, r[key])
assert int(r["steps"]) > 0, r["steps"]
assert float(r["pull_input_age_max_ms"]) > 0, r       # the coupler used the grab's snapshots
assert float(r["rss_mb"]) > 1, r
print("launcher_sessions smoke: ok", dict(r))
PY
