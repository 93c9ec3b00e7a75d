# Sourced by the measurement scripts once their arguments are resolved:
#   source "$(dirname "$0")/netns_lo.sh" ARGS...
# re-runs the calling script with ARGS inside a private network namespace (unshare -n; needs root) and
# there brings up loopback multicast, so udpm never leaves the machine; sets url to a ttl=0 udpm group.
if [ -z "${HAPTREE_IN_NETNS:-}" ]; then
  exec unshare -n env HAPTREE_IN_NETNS=1 bash "$0" "$@"
fi
ip link set lo up
ip link set lo multicast on
ip route add 224.0.0.0/4 dev lo
url="udpm://239.255.76.67:7667?ttl=0"
