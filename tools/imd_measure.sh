#!/bin/bash
# CPU cost of imd_bridge serving bacteriorhodopsin to one receiver (docs/imd.md). As root, in a private
# network namespace (udpm never leaves it):  unshare -n bash tools/imd_measure.sh VERSION [--no-forces]
# Run from the repository root after building into build/.
set -euo pipefail
VERSION=${1:-2}
EXTRA=${2:-}
B=${BUILD_DIR:-build}
URL='udpm://239.255.76.67:7667?ttl=0'
if ip route show default | grep -q .; then echo "run inside 'unshare -n' (no default route)"; exit 2; fi
ip link set lo up
ip route add 224.0.0.0/4 dev lo 2>/dev/null || true
"$B/sim_server/sim_server" --lcm-url "$URL" --scene bacteriorhodopsin --dt 0.0005 --users 1 --display-rate-hz 30 \
  > /tmp/imd_measure_sim.log 2>&1 &
SIM=$!
"$B/imd_bridge/imd_bridge" --lcm-url "$URL" --scene bacteriorhodopsin --imd-user 0 --imd-port 8888 \
  --imd-version "$VERSION" $EXTRA > /tmp/imd_measure_bridge.log 2>&1 &
IMD=$!
for _ in $(seq 200); do grep -q "serving" /tmp/imd_measure_bridge.log && break; sleep 0.1; done
sleep 1
t0=$(awk '{print $14+$15}' "/proc/$IMD/stat")
/usr/bin/python3 tools/imd_probe.py --port 8888 --seconds 20
t1=$(awk '{print $14+$15}' "/proc/$IMD/stat")
echo "imd_bridge CPU during the 20 s: $((t1 - t0)) ticks of 1/$(getconf CLK_TCK) s"
kill "$IMD" "$SIM"
wait || true
tail -1 /tmp/imd_measure_bridge.log
