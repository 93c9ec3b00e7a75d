#!/usr/bin/env bash
# Makes docs/img/lcm-spy.png: a live 2-user haptree_run session over udpm and scripts/lcm-spy.sh on it,
# both inside a private network namespace (nothing leaves the machine; needs root), lcm-spy on Xvfb,
# screenshot by java/Screenshot.java after DELAY_MS. Needs xvfb and a full (non-headless) JRE.
#   sudo java/spy_screenshot.sh OUT.png [DELAY_MS]
set -euo pipefail
out="$(realpath -m "${1:?usage: spy_screenshot.sh OUT.png [DELAY_MS]}")"
delay="${2:-9000}"
cd "$(dirname "$0")/.."
exec unshare -n bash -c '
set -e
ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo
URL="udpm://239.255.76.67:7667?ttl=0"
build/launcher/haptree_run --lcm-url "$URL" --duration-s 25 --users 2 > /tmp/spy_session.log 2>&1 &
S=$!
xvfb-run -a -s "-screen 0 800x600x24" bash -c "scripts/lcm-spy.sh --lcm-url \"$URL\" > /tmp/spy.log 2>&1 & sleep 1; java java/Screenshot.java '"$out"' '"$delay"'; kill %1"
wait $S || true
'
