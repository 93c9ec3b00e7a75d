#!/usr/bin/env bash
# Measures the coupler watchdog's false trips on this machine for several --stale-after-s values
# (issue 11, defect 3): runs `haptree_run --processes` (the real sim_server, coupler and device_bridge
# executables: device link over shared memory, the rest over the launcher's 127.0.0.1 tcpq hub) for
# DURATION seconds per value and prints, from the coupler's final log line, the watchdog trips per second
# and the fraction of feedback sent while grabbing that the watchdog zeroed. Nothing was stopped or
# delayed on purpose: every trip is a false one.
#   scripts/measure_stale_after.sh [BUILD_DIR] [DURATION_S] [VALUES...]
set -euo pipefail
build=${1:-build}
duration=${2:-12}
shift 2 2>/dev/null || true
values=("$@")
[ ${#values[@]} -gt 0 ] || values=(0.005 0.01 0.02 0.05 0.1)
printf "%-14s %8s %10s %14s %12s %10s\n" stale_after_s trips trips_per_s zeroed_feedback fraction restarts
for s in "${values[@]}"; do
  dir=$(mktemp -d /tmp/stale_after.XXXXXX)
  "$build/tools/haptree_run" --processes --duration-s "$duration" --stale-after-s "$s" --log-dir "$dir" >"$dir/run.out" 2>&1 || {
    echo "haptree_run failed for $s (see $dir)"; continue; }
  line=$(grep -h "coupler: .* iterations" "$dir/coupler_0.log" | tail -1)
  trips=$(sed -E 's/.* ([0-9]+) watchdog trips.*/\1/' <<<"$line")
  restarts=$(sed -E 's/.* ([0-9]+) restarts.*/\1/' <<<"$line")
  zeros=$(sed -E 's/.* ([0-9]+) of ([0-9]+) feedbacks while grabbing.*/\1/' <<<"$line")
  grab=$(sed -E 's/.* ([0-9]+) of ([0-9]+) feedbacks while grabbing.*/\2/' <<<"$line")
  awk -v s="$s" -v t="$trips" -v d="$duration" -v z="$zeros" -v g="$grab" -v r="$restarts" \
    'BEGIN { printf "%-14s %8d %10.2f %8d/%-8d %11.3f%% %10d\n", s, t, t / d, z, g, g ? 100 * z / g : 0, r }'
  rm -rf "$dir"
done
