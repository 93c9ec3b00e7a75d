#!/usr/bin/env bash
# The coupler refuses gains above a device's limit at start: exit 2, a message naming the limit and
# the factor, before it touches the bus. Usage: coupler_limits_test.sh PATH/TO/coupler
set -uo pipefail
coupler=$1
out=$("$coupler" --lcm-url memq:// --device-model touch --stiffness 100 --device-damping-n-s-per-m 2 2>&1)
rc=$?
echo "$out"
[ "$rc" -eq 2 ] || { echo "expected exit 2, got $rc"; exit 1; }
grep -q "exceeds 400 N/m by a factor 1.25: the device's max stiffness on 3D Systems Touch" <<<"$out" || exit 1
grep -q "refusing to start" <<<"$out" || exit 1
out=$("$coupler" --lcm-url memq:// --device-model no_such_device 2>&1)
rc=$?
[ "$rc" -eq 2 ] && grep -q "known: simulated, touch" <<<"$out" || { echo "$out"; exit 1; }
echo "coupler device-limit refusals: ok"
