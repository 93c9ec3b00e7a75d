#!/usr/bin/env bash
# lcm-spy with haptree's message types on the classpath, so every HAPTREE_* channel is decoded.
# Debian's /usr/bin/lcm-spy passes -Xincgc, which Java >= 9 rejects ("Unrecognized option: -Xincgc").
#
#   scripts/lcm-spy.sh [--lcm-url URL] [other lcm.spy.Spy options]
#   scripts/lcm-spy.sh --lcm-url 'udpm://239.255.76.67:7667?ttl=0'     # the default URL if none is given
#
# The jar is build/java/haptree_lcmtypes.jar (cmake builds it when a JDK and liblcm-java are present);
# HAPTREE_LCMTYPES_JAR and LCM_JAR override the paths. Needs a display (X11; xvfb-run works).
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
types_jar="${HAPTREE_LCMTYPES_JAR:-$here/build/java/haptree_lcmtypes.jar}"
lcm_jar="${LCM_JAR:-/usr/share/java/lcm.jar}"
case "${1:-}" in
  -h|--help)
    sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'
    exit 0 ;;
esac
command -v java >/dev/null || { echo "lcm-spy.sh: java not found (install openjdk-17-jre)" >&2; exit 2; }
[ -f "$lcm_jar" ] || { echo "lcm-spy.sh: $lcm_jar not found (install liblcm-java, or set LCM_JAR)" >&2; exit 2; }
[ -f "$types_jar" ] || { echo "lcm-spy.sh: $types_jar not found: build it (cmake --build build --target haptree_lcmtypes_jar; needs javac and liblcm-java) or set HAPTREE_LCMTYPES_JAR" >&2; exit 2; }
if [ -z "${DISPLAY:-}" ]; then
  echo "lcm-spy.sh: no DISPLAY (lcm-spy is a Swing window; run under X11 or xvfb-run)" >&2
  exit 2
fi
cp="$lcm_jar:$types_jar"
[ -f /usr/share/java/jchart2d.jar ] && cp="$cp:/usr/share/java/jchart2d.jar"   # lcm-spy's plots, if installed
exec java -Djava.net.preferIPv4Stack=true -Xmx256m -cp "$cp" lcm.spy.Spy "$@"
