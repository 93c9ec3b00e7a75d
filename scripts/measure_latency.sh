#!/usr/bin/env bash
# Device pose -> feedback force latency through the real processes: coupler + device_bridge
# (scripted device, 1 kHz), over shared memory and over udpm, without and with a background load
# (`stress-ng --cpu 1`), for each real-time option set below. Latency = device_bridge publishing
# DEVICE_STATE seq k -> its receiving the first FEEDBACK that echoes k (bridge's steady clock,
# LatencyHistogram, 1/16-octave bins: percentiles are bin edges, ~4 % resolution). No sim_server: the coupler
# answers every pose with or without a snapshot, which is what the latency measures.
# Every run is inside a private network namespace (`unshare -n`, multicast route on lo): udpm never
# leaves the machine. Needs root (unshare; SCHED_FIFO and mlockall are refused otherwise, and said).
# Prints a table (median, p99, p99.9, samples, coupler rate, what was refused) and writes CSV.
#   scripts/measure_latency.sh [BUILD_DIR] [DURATION_S] [CSV] [FILTER]
# FILTER: a regex on "link/load/options" (e.g. 'shm/stress' or 'fifo'); default all.
set -euo pipefail
build=$(realpath "${1:-build}")
duration=${2:-8}
csv=${3:-latency.csv}
filter=${4:-.}
# shellcheck source=scripts/netns_lo.sh
source "$(dirname "$0")/netns_lo.sh" "$build" "$duration" "$csv" "$filter"
command -v stress-ng >/dev/null || { echo "stress-ng not installed (apt-get install stress-ng)" >&2; exit 2; }

# name | coupler options | device_bridge options   (coupler --rate-hz: 20 kHz on shm, 10 kHz on udpm, unless set)
shm_sets=(
  "busywait|--shm|--shm --busy-poll"
  "sleep|--shm --sleep|--shm --busy-poll"
  "busypoll|--shm --busy-poll|--shm --busy-poll"
  "fifo-sleep|--shm --sleep --sched-fifo 80|--shm --busy-poll --sched-fifo 81"
  "fifo-busypoll|--shm --busy-poll --sched-fifo 80|--shm --busy-poll --sched-fifo 81"
  "fifo-busypoll-pin|--shm --busy-poll --sched-fifo 80 --cpu-affinity 1|--shm --busy-poll --sched-fifo 81 --cpu-affinity 0"
  "fifo-busypoll-pin-mlock|--shm --busy-poll --sched-fifo 80 --cpu-affinity 1 --mlockall|--shm --busy-poll --sched-fifo 81 --cpu-affinity 0 --mlockall"
  "fifo-sleep-pin-mlock|--shm --sleep --sched-fifo 80 --cpu-affinity 1 --mlockall|--shm --busy-poll --sched-fifo 81 --cpu-affinity 0 --mlockall"
  "fifo-sleep40k-pin-mlock|--shm --sleep --rate-hz 40000 --sched-fifo 80 --cpu-affinity 1 --mlockall|--shm --busy-poll --sched-fifo 81 --cpu-affinity 0 --mlockall"
)
udpm_sets=(
  "busywait||"
  "sleep|--sleep|"
  "sleep-slack|--sleep --timer-slack-ns 1000|--timer-slack-ns 1000"
  "busypoll|--busy-poll|"
  "fifo-sleep|--sleep --sched-fifo 80|--sched-fifo 81"
  "fifo-busypoll|--busy-poll --sched-fifo 80|--sched-fifo 81"
  "fifo-sleep-pin-mlock|--sleep --sched-fifo 80 --cpu-affinity 1 --mlockall|--sched-fifo 81 --cpu-affinity 0 --mlockall"
  "fifo-busypoll-pin-mlock|--busy-poll --sched-fifo 80 --cpu-affinity 1 --mlockall|--sched-fifo 81 --cpu-affinity 0 --mlockall"
)

echo "link,load,options,coupler_options,bridge_options,p50_us,p99_us,p999_us,samples,coupler_rate_hz,load1,refused" >"$csv"
printf "%-5s %-6s %-24s %9s %9s %9s %7s %9s %5s %s\n" link load options p50_us p99_us p99.9_us samples rate_hz load1 refused
run() {   # link load name copts dopts rate
  local link=$1 load=$2 name=$3 copts=$4 dopts=$5 rate=$6
  [[ "$link/$load/$name" =~ $filter ]] || return 0
  local dir stress="" cpl line it p50 p99 p999 n refused load1
  dir=$(mktemp -d /tmp/latency.XXXXXX)
  if [ "$load" = stress ]; then
    stress-ng --cpu 1 --timeout $((duration + 5)) >/dev/null 2>&1 &
    stress=$!
    sleep 0.5
  fi
  [[ "$copts" == *--rate-hz* ]] && rate=$(sed -E 's/.*--rate-hz ([0-9]+).*/\1/' <<<"$copts") && copts=${copts/--rate-hz $rate/}
  # shellcheck disable=SC2086
  "$build/coupler/coupler" --lcm-url "$url" --rate-hz "$rate" $copts >"$dir/coupler.log" 2>&1 &
  cpl=$!
  sleep 0.3
  # shellcheck disable=SC2086
  timeout -s INT "$duration" "$build/device_bridge/device_bridge" --lcm-url "$url" --rate-hz 1000 $dopts \
    >"$dir/device.log" 2>&1 || true
  load1=$(cut -d' ' -f1 /proc/loadavg)
  kill -INT "$cpl"; wait "$cpl" || true
  if [ -n "$stress" ]; then kill -TERM "$stress" 2>/dev/null || true; wait "$stress" 2>/dev/null || true; fi
  line=$(grep -h "device_bridge: .* readings" "$dir/device.log" | tail -1)
  p50=$(sed -nE 's/.*latency p50 ([0-9.]+) us.*/\1/p' <<<"$line")
  p99=$(sed -nE 's/.* p99 ([0-9.]+) us \(.*/\1/p' <<<"$line")
  n=$(sed -nE 's/.*\(([0-9]+) samples\).*/\1/p' <<<"$line")
  p999=$(sed -nE 's/.*p99\.9 ([0-9.]+) us.*/\1/p' <<<"$line")
  it=$(sed -nE 's/.*coupler: ([0-9]+) iterations.*/\1/p' "$dir/coupler.log" | tail -1)
  # which real-time options were refused, in short (the full words are in the logs)
  refused=$(grep -hoE "real-time: [^ ]+( [^ ]+)? refused" "$dir/coupler.log" "$dir/device.log" | sort -u |
            sed -E 's/real-time: //; s/ refused//' | paste -sd';' - || true)
  local rate_meas
  rate_meas=$(awk -v i="${it:-0}" -v d="$duration" 'BEGIN { printf "%.0f", i / (d + 0.3) }')
  printf "%-5s %-6s %-24s %9s %9s %9s %7s %9s %5s %s\n" "$link" "$load" "$name" "${p50:-nan}" "${p99:-nan}" \
    "${p999:-nan}" "${n:-0}" "$rate_meas" "$load1" "${refused:--}"
  echo "$link,$load,$name,\"$copts\",\"$dopts\",${p50:-nan},${p99:-nan},${p999:-nan},${n:-0},$rate_meas,$load1,\"${refused}\"" >>"$csv"
  rm -rf "$dir"
}
# The machine's own floor: wake-up latency of a SCHED_FIFO 80 timer thread per CPU (cyclictest, Debian
# rt-tests), 1 ms interval, same duration and load. What a preempted vCPU or a long interrupt costs shows
# here too, and no option of ours can remove it.
floor() {   # load
  local load=$1 stress=""
  [[ "floor/$load" =~ $filter ]] || return 0
  command -v cyclictest >/dev/null || { echo "floor/$load: cyclictest not installed (apt-get install rt-tests)"; return 0; }
  if [ "$load" = stress ]; then
    stress-ng --cpu 1 --timeout $((duration + 5)) >/dev/null 2>&1 &
    stress=$!
    sleep 0.5
  fi
  local out
  out=$(mktemp /tmp/latency.XXXXXX)
  cyclictest -m -t 2 -a 0,1 -p 80 -i 1000 -D "$duration" -q -h 5000 >"$out" 2>&1 || true
  if [ -n "$stress" ]; then kill -TERM "$stress" 2>/dev/null || true; wait "$stress" 2>/dev/null || true; fi
  local load1
  load1=$(cut -d' ' -f1 /proc/loadavg)
  for cpu in 0 1; do
    awk -v c=$((cpu + 2)) -v cpu=$cpu -v load="$load" -v l1="$load1" -v csv="$csv" '
      !/^#/ && NF >= 3 { n[$1 + 0] = $c + 0; tot += $c }
      END {
        acc = 0; p50 = p99 = p999 = "nan"
        for (us = 0; us < 5000; ++us) { acc += n[us]
          if (p50 == "nan" && acc >= 0.5 * tot) p50 = us
          if (p99 == "nan" && acc >= 0.99 * tot) p99 = us
          if (p999 == "nan" && acc >= 0.999 * tot) p999 = us }
        if (p999 == "nan") p999 = ">5000"
        name = "cyclictest-fifo80-cpu" cpu
        printf "%-5s %-6s %-24s %9s %9s %9s %7d %9s %5s %s\n", "floor", load, name, p50, p99, p999, tot, "-", l1, "-"
        printf "floor,%s,%s,\"\",\"\",%s,%s,%s,%d,,%s,\"\"\n", load, name, p50, p99, p999, tot, l1 >> csv
      }' "$out"
  done
  rm -f "$out"
}
for load in none stress; do
  floor "$load"
  for s in "${shm_sets[@]}"; do IFS='|' read -r name copts dopts <<<"$s"; run shm "$load" "$name" "$copts" "$dopts" 20000; done
  for s in "${udpm_sets[@]}"; do IFS='|' read -r name copts dopts <<<"$s"; run udpm "$load" "$name" "$copts" "$dopts" 10000; done
done
echo "CSV: $csv"
