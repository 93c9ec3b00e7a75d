#!/usr/bin/env bash
# CPU time and context switches of every coupler thread in a coupler + device_bridge session over udpm
# (inside `unshare -n`, multicast on lo only), read from /proc/PID/task/* near the end of the run: what a
# handler-thread path costs (e.g. the second-writer check on the coupler's own FEEDBACK),
# independent of the latency noise of a loaded machine. The bridge's pose->force latency line is printed too.
#   scripts/measure_thread_cost.sh [BUILD_DIR] [DURATION_S] ["COUPLER OPTIONS"] ["BRIDGE OPTIONS"]
# BUILD_DIR needs coupler/coupler and device_bridge/device_bridge. Needs root (unshare).
set -euo pipefail
build=$(realpath "${1:-build}")
duration=${2:-8}
copts=${3:-}
dopts=${4:-}
# shellcheck source=scripts/netns_lo.sh
source "$(dirname "$0")/netns_lo.sh" "$build" "$duration" "$copts" "$dopts"
dir=$(mktemp -d /tmp/threadcost.XXXXXX)
# shellcheck disable=SC2086
"$build/coupler/coupler" --lcm-url "$url" --rate-hz 10000 $copts >"$dir/coupler.log" 2>&1 &
cpl=$!
sleep 0.3
# shellcheck disable=SC2086
timeout -s INT "$duration" "$build/device_bridge/device_bridge" --lcm-url "$url" --rate-hz 1000 $dopts \
  >"$dir/device.log" 2>&1 &
dev=$!
sleep $((duration - 1))
hz=$(getconf CLK_TCK)
printf "%-8s %-10s %10s %12s %12s\n" tid role cpu_s_per_s vol_cs_per_s invol_cs_per_s
elapsed=$(awk -v s="$(cut -d' ' -f22 /proc/$cpl/stat)" -v hz="$hz" '{ printf "%.3f", $1 - s / hz }' /proc/uptime)
for t in /proc/$cpl/task/*; do
  tid=${t##*/}
  role=other
  [ "$tid" = "$cpl" ] && role=loop
  read -r ut st < <(awk '{ print $14, $15 }' "$t/stat")
  vol=$(awk '/^voluntary_ctxt_switches/ { print $2 }' "$t/status")
  inv=$(awk '/^nonvoluntary_ctxt_switches/ { print $2 }' "$t/status")
  awk -v tid="$tid" -v role="$role" -v ut="$ut" -v st="$st" -v hz="$hz" -v e="$elapsed" -v vol="$vol" -v inv="$inv" \
    'BEGIN { printf "%-8s %-10s %10.3f %12.0f %12.0f\n", tid, role, (ut + st) / hz / e, vol / e, inv / e }'
done
wait "$dev" || true
kill -INT "$cpl"; wait "$cpl" || true
grep -h "device_bridge: .* readings" "$dir/device.log" | tail -1
grep -h "coupler: .* iterations" "$dir/coupler.log" | tail -1
rm -rf "$dir"
