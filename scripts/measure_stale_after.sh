#!/usr/bin/env bash
# Measures the coupler watchdog's false trips on this machine for several --stale-after-s values
# with the by-hand commands of docs/processes.md: sim_server, coupler (default
# busy-wait pacing at 10 kHz) and device_bridge as separate processes over udpm ttl=0, device link over
# shared memory. udpm stays inside a private network namespace (`unshare -n`, multicast route on lo): needs
# root. The scripted user grabs the last body of protein_like(64) and holds the pull for the whole run;
# nothing is stopped or delayed on purpose, so every watchdog trip is a false one. The coupler is stopped
# first, so the shutdown itself trips nothing. Prints, per value: watchdog trips, trips per second, the
# feedback sent while grabbing that the watchdog zeroed (count and fraction), server restarts taken, the
# longest gap between two USER_FORCE messages seen by sim_server, and the 1-minute load average.
#   scripts/measure_stale_after.sh [BUILD_DIR] [DURATION_S] [VALUES...]
set -euo pipefail
build=$(realpath "${1:-build}")
duration=${2:-12}
shift 2 2>/dev/null || true
values=("$@")
[ ${#values[@]} -gt 0 ] || values=(0.005 0.01 0.02 0.05 0.1)
# shellcheck source=scripts/netns_lo.sh
source "$(dirname "$0")/netns_lo.sh" "$build" "$duration" "${values[@]}"
# Grab geometry: the device's grab waypoint (0, 0, 0.01 m) x position scale 10 onto the last body at q = 0.
# The body's origin comes from the launcher's embedded run (its coupler logs the offset it was given).
probe=$(mktemp -d /tmp/stale_after.XXXXXX)
"$build/launcher/haptree_run" --duration-s 1 --n 64 >"$probe/run.out" 2>&1
body=$(sed -nE 's/.*pulling bodies ([0-9]+).*/\1/p' "$probe/run.out" | head -1)
read -r ox oy oz < <(sed -nE 's/.*mapping: scene = [0-9.]+ x device_m \+ \[([^ ]+) ([^ ]+) ([^]]+)\].*/\1 \2 \3/p' \
                     "$probe/run.out" | head -1)
rm -rf "$probe"
echo "protein_like(64): grab body $body, offset $ox $oy $oz; ${duration} s per value"
printf "%-14s %6s %11s %17s %10s %9s %14s %6s\n" stale_after_s trips trips_per_s zeroed_feedback fraction restarts \
  uf_gap_max_ms load1
for s in "${values[@]}"; do
  dir=$(mktemp -d /tmp/stale_after.XXXXXX)
  "$build/sim_server/sim_server" --lcm-url "$url" --scene protein_like --n 64 --sim-rate-hz 1000 >"$dir/sim.log" 2>&1 &
  sim=$!
  "$build/coupler/coupler" --lcm-url "$url" --grab-body "$body" --offset "$ox" "$oy" "$oz" --shm \
    --stale-after-s "$s" >"$dir/coupler.log" 2>&1 &
  cpl=$!
  "$build/device_bridge/device_bridge" --lcm-url "$url" --device-kind scripted --shm --device-option hold_s=600 \
    >"$dir/device.log" 2>&1 &
  dev=$!
  sleep "$duration"
  kill -TERM "$cpl"; wait "$cpl" || true
  kill -TERM "$dev" "$sim"; wait "$dev" "$sim" || true
  line=$(grep -h "coupler: .* iterations" "$dir/coupler.log" | tail -1)
  trips=$(sed -E 's/.* ([0-9]+) watchdog trips.*/\1/' <<<"$line")
  restarts=$(sed -E 's/.* ([0-9]+) restarts.*/\1/' <<<"$line")
  zeros=$(sed -E 's/.* ([0-9]+) of ([0-9]+) feedbacks while grabbing.*/\1/' <<<"$line")
  grab=$(sed -E 's/.* ([0-9]+) of ([0-9]+) feedbacks while grabbing.*/\2/' <<<"$line")
  gap=$(grep -h "longest USER_FORCE gap" "$dir/sim.log" | tail -1 | sed -E 's/.*gap ([0-9.]+) ms.*/\1/')
  load=$(cut -d' ' -f1 /proc/loadavg)
  awk -v s="$s" -v t="$trips" -v d="$duration" -v z="$zeros" -v g="$grab" -v r="$restarts" -v gap="${gap:-nan}" \
    -v load="$load" 'BEGIN { printf "%-14s %6d %11.2f %8d/%-8d %9.3f%% %9d %14s %6s\n", s, t, t / d, z, g,
                             g ? 100 * z / g : 0, r, gap, load }'
  rm -rf "$dir"
done
