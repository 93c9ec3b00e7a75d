#!/usr/bin/env bash
# The installed haptree, used as a user would (CTest: install_package, label install):
#  1. cmake --install BUILD into a fresh temporary prefix; the systemd unit templates' command lines
#     run as systemd would run them (the installed example session file, --print-config), and
#     systemd-analyze verify where it is installed;
#  2. examples/consumer built against that prefix alone (find_package(haptree)), with plain -O2 and no
#     -march whatever the library's flags, shared and static, and every installed header compiled;
#     the consumer runs (URDF -> forward_dynamics vs inverse dynamics, a coupling call); once more
#     with -march=native (on a CPU with AVX: Eigen's alignment would differ from an x86-64-v2 library);
#  3. the same program built with pkg-config's flags (haptree.pc);
#  4. the installed haptree_run --duration-s 3 on a molecule with its viewer on, from another working
#     directory with no HAPTREE_* variable, the source and build trees hidden behind an empty tmpfs
#     (private mount namespace; root or user namespaces needed, else it says it only changed directory);
#     the viewer's page and NGL are fetched from it with the token of its token file (refused without);
#  5. cpack -G DEB: the packages' control fields and contents checked (dpkg-deb -I / -c); with
#     HAPTREE_TEST_DPKG_INSTALL=1 (scripts/test.sh as root) they are installed with dpkg -i, the
#     installed programs run, and purged again (with the user and /etc/haptree their postinst made).
# Usage: scripts/test_install.sh [BUILD_DIR]   (default: build)
set -euo pipefail
# Under pipefail, "producer | grep -q" fails at random: grep -q exits at its first match and the
# producer, still writing, dies of SIGPIPE. Hence "| grep PATTERN > /dev/null" below (reads it all).
SRC=$(cd "$(dirname "$0")/.." && pwd)
BUILD=$(cd "${1:-$SRC/build}" && pwd)
WORK=$(mktemp -d /tmp/haptree-install.XXXXXX)
CLEANUP=()   # commands run at exit, whatever the outcome (the packages' purge once they are installed)
trap 'for c in "${CLEANUP[@]}"; do eval "$c" || true; done; rm -rf "$WORK"' EXIT
PREFIX=$WORK/prefix
fail() { echo "test_install: FAIL: $*" >&2; exit 1; }
step() { echo "== test_install [${SECONDS} s]: $*"; }

step "cmake --install into $PREFIX"
cmake --install "$BUILD" --prefix "$PREFIX" > "$WORK/install.log" || { cat "$WORK/install.log"; fail "cmake --install"; }
for f in bin/sim_server bin/coupler bin/device_bridge bin/viewer bin/imd_bridge bin/haptree_run bin/haptree-fd \
         bin/replay_coupling bin/trajectory_from_log include/haptree/dca.hpp include/haptree/io/urdf.hpp \
         include/haptree/lcmt_feedback.hpp share/haptree/lcmtypes/lcmt_feedback.lcm \
         share/haptree/data/molecules/ff14sb.dat share/haptree/viewer/web/index.html \
         share/haptree/viewer/web/vendor/ngl.js share/haptree/models/arm.urdf; do
  [ -e "$PREFIX/$f" ] || fail "not installed: $f"
done
LIBDIR=$(dirname "$(find "$PREFIX" -name libhaptree.so -print -quit)")
[ -n "$LIBDIR" ] || fail "libhaptree.so not installed"
for l in haptree haptree_io haptree_molecule haptree_bus haptree_device haptree_imd; do
  [ -e "$LIBDIR/lib$l.a" ] || fail "static lib$l.a not installed"
  soname=$(objdump -p "$LIBDIR/lib$l.so" | awk '/SONAME/ {print $2}')
  [ -n "$soname" ] && [ -e "$LIBDIR/$soname" ] || fail "lib$l.so: no SONAME or no $soname"
done
[ -e "$LIBDIR/cmake/haptree/haptreeConfig.cmake" ] && [ -e "$LIBDIR/cmake/haptree/haptreeConfigVersion.cmake" ] \
  || fail "CMake package files"
[ -e "$LIBDIR/pkgconfig/haptree.pc" ] || fail "haptree.pc"
find "$PREFIX" -name '_core*.so' -path '*haptree*' | grep . > /dev/null || fail "Python extension not installed"

step "systemd unit templates: their command line, run as systemd would run it"
# ExecStart with CONFIG (the instance's session file, here the installed example) and ARGS (empty, then
# the example's second user) expanded, plus --print-config: the program reads the file and exits 0.
SESSION=$PREFIX/share/haptree/examples/sessions/two_hosts.toml
[ -e "$SESSION" ] && [ -e "$PREFIX/share/haptree/systemd/example.conf" ] || fail "example session or example.conf not installed"
for p in sim_server coupler device_bridge; do
  unit=$PREFIX/lib/systemd/system/$p@.service
  [ -e "$unit" ] || fail "not installed: $unit"
  grep -qx "Environment=CONFIG=/etc/haptree/%i.toml" "$unit" || fail "$p@.service: no default CONFIG=/etc/haptree/%i.toml"
  grep -qx "EnvironmentFile=-/etc/haptree/$p-%i.conf" "$unit" || fail "$p@.service: no optional /etc/haptree/$p-%i.conf"
  exec_start=$(sed -n 's/^ExecStart=//p' "$unit")
  [ "$exec_start" = "$PREFIX/bin/$p --config \${CONFIG} \$ARGS" ] || fail "$p@.service: ExecStart=$exec_start"
  case $p in coupler) extra="--user 1" ;; device_bridge) extra="--device 1" ;; *) extra="" ;; esac
  for args in "" "$extra"; do
    # shellcheck disable=SC2086  # ARGS is split into words, as systemd splits $ARGS
    (cd "$WORK" && "$PREFIX/bin/$p" --config "$SESSION" $args --print-config > "$WORK/unit-$p.out" 2>&1) \
      || { cat "$WORK/unit-$p.out"; fail "$p --config $SESSION $args --print-config"; }
  done
  grep -q "^lcm-url" "$WORK/unit-$p.out" || { cat "$WORK/unit-$p.out"; fail "$p --print-config: no lcm-url"; }
done
if command -v systemd-analyze > /dev/null 2>&1; then
  # Syntax and directives (an instance of each template; the haptree user need not exist here).
  mkdir -p "$WORK/units"
  for p in sim_server coupler device_bridge; do cp "$PREFIX/lib/systemd/system/$p@.service" "$WORK/units/"; done
  (cd "$WORK/units" && SYSTEMD_LOG_LEVEL=warning systemd-analyze verify --man=no \
      sim_server@lab1.service coupler@lab1.service device_bridge@lab1.service) > "$WORK/verify.log" 2>&1 \
    || true
  if grep -E "Unknown (key|section)|Invalid|Failed to parse|bad-setting" "$WORK/verify.log"; then
    fail "systemd-analyze verify found errors in the unit templates"
  fi
fi

step "examples/consumer against the prefix only (-O2, no -march)"
# No CMAKE_PREFIX_PATH from the environment, nothing of the source or build tree on the include path:
# the consumer sees the prefix and the system, like a user's project.
cp -r "$SRC/examples/consumer" "$WORK/consumer-src"   # a copy: nothing next to it from the tree
env -u CMAKE_PREFIX_PATH CXXFLAGS="-O2" \
  cmake -S "$WORK/consumer-src" -B "$WORK/consumer" -DCMAKE_BUILD_TYPE= -DCMAKE_PREFIX_PATH="$PREFIX" \
        -DCMAKE_CXX_FLAGS="-O2" > "$WORK/consumer.log" 2>&1 || { cat "$WORK/consumer.log"; fail "consumer configure"; }
cmake --build "$WORK/consumer" -j "${HAPTREE_JOBS:-2}" >> "$WORK/consumer.log" 2>&1 \
  || { tail -40 "$WORK/consumer.log"; fail "consumer build"; }
if grep -hE -- "-march|$SRC" "$WORK/consumer"/CMakeFiles/*.dir/flags.make "$WORK/consumer"/CMakeFiles/*.dir/link.txt; then
  fail "the consumer's flags mention -march or the source tree"
fi
MODEL=$PREFIX/share/haptree/models/arm.urdf
(cd "$WORK" && "$WORK/consumer/consumer" "$MODEL") || fail "consumer (shared) run"
ldd "$WORK/consumer/consumer" | grep "$LIBDIR/libhaptree.so" > /dev/null || fail "consumer does not use the installed libhaptree.so"
(cd "$WORK" && "$WORK/consumer/consumer_static" "$MODEL") || fail "consumer (static) run"

# The other side of the flags: a consumer built for this CPU (AVX/AVX-512 where it has them) against a
# library built for another level would pick other Eigen alignments without the package's definitions.
if grep -qw avx /proc/cpuinfo; then
  cmake -S "$WORK/consumer-src" -B "$WORK/consumer-native" -DCMAKE_BUILD_TYPE= -DCMAKE_PREFIX_PATH="$PREFIX" \
        -DCMAKE_CXX_FLAGS="-O2 -march=native" > "$WORK/consumer-native.log" 2>&1 \
    && cmake --build "$WORK/consumer-native" --target consumer >> "$WORK/consumer-native.log" 2>&1 \
    || { tail -40 "$WORK/consumer-native.log"; fail "consumer (-march=native) build"; }
  (cd "$WORK" && "$WORK/consumer-native/consumer" "$MODEL" | tail -1) || fail "consumer (-march=native) run"
fi

step "pkg-config haptree"
export PKG_CONFIG_PATH=$LIBDIR/pkgconfig
# shellcheck disable=SC2046
c++ -std=c++17 -O2 -o "$WORK/consumer_pc" "$WORK/consumer-src/main.cpp" $(pkg-config --cflags --libs haptree) \
    -Wl,-rpath,"$LIBDIR" || fail "build with pkg-config flags"
"$WORK/consumer_pc" "$MODEL" > /dev/null || fail "consumer (pkg-config) run"
unset PKG_CONFIG_PATH

step "installed haptree_run, source tree out of reach"
PORT=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
mkdir -p "$WORK/run"
TOKEN=$(od -An -N16 -tx1 /dev/urandom | tr -d ' \n')
echo "$TOKEN" > "$WORK/run/viewer.token"
cat > "$WORK/run/session.sh" <<EOF
set -e
cd "$WORK/run"
for d in "$SRC" "$BUILD"; do [ -d "\$d" ] && mount -t tmpfs none "\$d" || true; done
[ -e "$SRC/CMakeLists.txt" ] && echo "source tree still visible" >&2 && exit 1
"$PREFIX/bin/haptree_run" --duration-s 3 --scene ala20 --dt 0.0005 --position-scale 1 --stiffness 200 \
    --viewer-port $PORT --viewer-token-file "$WORK/run/viewer.token" > session.log 2>&1 &
pid=\$!
python3 - <<'PY'
import time, urllib.error, urllib.request
for path, must in (("/", b"<html"), ("/vendor/ngl.js", b"NGL")):
    deadline = time.time() + 60   # the launcher loads its molecule first: slow on a loaded machine
    while True:
        try:
            body = urllib.request.urlopen("http://127.0.0.1:$PORT" + path + "?token=$TOKEN", timeout=5).read()
            break
        except OSError:
            if time.time() > deadline:
                raise SystemExit("viewer did not answer " + path + " within 60 s")
            time.sleep(0.1)
    if must not in body[:200000]:
        raise SystemExit("viewer page " + path + " lacks " + must.decode())
try:
    urllib.request.urlopen("http://127.0.0.1:$PORT/", timeout=2)
    raise SystemExit("viewer served / without its token")
except urllib.error.HTTPError:
    pass
print("viewer served / and /vendor/ngl.js with the token from the token file, refused / without it")
PY
wait \$pid
EOF
CLEAN_ENV=(env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME="$WORK/run" LANG=C.UTF-8)
if [ "$(id -u)" -eq 0 ] && unshare -m true 2>/dev/null; then
  how="mount namespace (root)"; runner=(unshare -m --propagation private)
elif unshare -rm true 2>/dev/null; then
  how="user + mount namespace"; runner=(unshare -rm --propagation private)
else
  how="other directory only (no namespaces here: the trees stay visible)"; runner=()
  sed -i '/mount -t tmpfs/d; /source tree still visible/d' "$WORK/run/session.sh"
fi
echo "   ($how)"
"${CLEAN_ENV[@]}" "${runner[@]}" bash "$WORK/run/session.sh" || { tail -30 "$WORK/run/session.log"; fail "installed haptree_run"; }
grep -q "scene ala20" "$WORK/run/session.log" || { tail -30 "$WORK/run/session.log"; fail "haptree_run did not load ala20"; }
tail -3 "$WORK/run/session.log"

step "Debian packages (cpack -G DEB)"
for tool in file dpkg-shlibdeps; do   # without them cpack leaves Depends: out, with a warning only
  command -v $tool > /dev/null || fail "cpack needs $tool for Depends: (scripts/install_deps.sh --tests installs it)"
done
(cd "$BUILD" && cpack -G DEB -B "$WORK/deb" > "$WORK/cpack.log" 2>&1) || { tail -40 "$WORK/cpack.log"; fail "cpack"; }
ls "$WORK"/deb/*.deb
deb() { ls "$WORK"/deb/"$1"_*.deb 2>/dev/null | head -1; }
RT=$(deb haptree); DEV=$(deb haptree-dev); PY=$(deb python3-haptree)
[ -n "$RT" ] && [ -n "$DEV" ] && [ -n "$PY" ] || fail "expected haptree, haptree-dev, python3-haptree .debs"
dpkg-deb -I "$RT" > "$WORK/rt.info"; dpkg-deb -c "$RT" > "$WORK/rt.list"
dpkg-deb -I "$DEV" > "$WORK/dev.info"; dpkg-deb -c "$DEV" > "$WORK/dev.list"
dpkg-deb -I "$PY" > "$WORK/py.info"; dpkg-deb -c "$PY" > "$WORK/py.list"
grep "Depends:" "$WORK/rt.info"
for dep in liblcm1 libsodium23 liburdfdom-model libgomp1 libspdlog1; do
  grep "^ Depends:" "$WORK/rt.info" | grep "$dep" > /dev/null || fail "runtime Depends lacks $dep (dpkg-shlibdeps)"
done
grep "^ Depends:" "$WORK/rt.info" | grep -Eq "openjdk|default-jre|java" && fail "runtime depends on Java"
grep "^ Depends:" "$WORK/dev.info" | grep "haptree (= " > /dev/null || fail "haptree-dev does not depend on haptree (= version)"
for f in ./usr/bin/sim_server ./usr/bin/coupler ./usr/bin/device_bridge ./usr/bin/haptree_run \
         ./usr/share/haptree/viewer/web/vendor/ngl.js ./usr/share/haptree/data/molecules/ff14sb.dat \
         ./usr/lib/systemd/system/sim_server@.service ./usr/lib/systemd/system/coupler@.service \
         ./usr/lib/systemd/system/device_bridge@.service ./usr/share/man/man1/sim_server.1.gz; do
  grep -q " $f\$" "$WORK/rt.list" || fail "runtime package lacks $f"
done
grep -Eq "libhaptree\.so\.[0-9]" "$WORK/rt.list" || fail "runtime package lacks libhaptree.so.N"
grep -Eq "\.a$|/include/" "$WORK/rt.list" && fail "runtime package holds headers or static libs"
for f in include/haptree/dca.hpp haptree/haptreeConfig.cmake pkgconfig/haptree.pc libhaptree.a libhaptree.so; do
  grep -qE "$f( -> .*)?\$" "$WORK/dev.list" || fail "dev package lacks $f"   # a symlink: "name -> target"
done
grep -q "dist-packages/haptree/__init__.py" "$WORK/py.list" || fail "python package lacks the module"
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep "install ok installed" > /dev/null; }
if [ "${HAPTREE_TEST_DPKG_INSTALL:-0}" = 1 ] && { installed haptree || installed haptree-dev || installed python3-haptree; }; then
  echo "   dpkg -i skipped: a haptree package is already installed on this machine"
elif [ "${HAPTREE_TEST_DPKG_INSTALL:-0}" = 1 ]; then
  step "dpkg -i (HAPTREE_TEST_DPKG_INSTALL=1), run, purge"
  # What the packages' postinst adds to the machine (the service user, /etc/haptree) is taken away
  # again after the purge when it was not there before.
  had_user=0; getent passwd haptree > /dev/null && had_user=1
  had_group=0; getent group haptree > /dev/null && had_group=1
  had_etc=0; [ -e /etc/haptree ] && had_etc=1
  purge() {
    dpkg --purge python3-haptree haptree-dev haptree > "$WORK/purge.log" 2>&1 || { cat "$WORK/purge.log"; return 1; }
    [ $had_user = 1 ] || ! getent passwd haptree > /dev/null || userdel haptree || return 1
    [ $had_group = 1 ] || ! getent group haptree > /dev/null || groupdel haptree || return 1
    [ $had_etc = 1 ] || rmdir /etc/haptree 2> /dev/null || [ ! -e /etc/haptree ] || return 1
  }
  CLEANUP+=("{ dpkg-query -W haptree || dpkg-query -W haptree-dev || dpkg-query -W python3-haptree; } > /dev/null 2>&1 && purge")
  dpkg -i "$RT" "$DEV" "$PY" > "$WORK/dpkg.log" 2>&1 || { cat "$WORK/dpkg.log"; fail "dpkg -i"; }
  ok=1
  getent passwd haptree > /dev/null || { echo "postinst did not create the haptree user"; ok=0; }
  (cd / && env -i PATH=/usr/bin:/bin /usr/bin/haptree-fd --urdf /usr/share/haptree/models/arm.urdf > /dev/null) || ok=0
  (cd / && env -i PATH=/usr/bin:/bin /usr/bin/sim_server --config /usr/share/haptree/examples/sessions/two_hosts.toml \
      --print-config > /dev/null) || ok=0
  (cd / && env -i PATH=/usr/bin:/bin /usr/bin/python3 -c 'import haptree; print("python3 haptree:", haptree.data_dir())') || ok=0
  # The -dev package as a user has it: pkg-config's default path, the shared libraries found by the
  # dynamic loader without an rpath.
  # shellcheck disable=SC2046
  (cd "$WORK" && c++ -std=c++17 -O2 -o consumer_usr consumer-src/main.cpp $(env -i PATH=/usr/bin:/bin pkg-config --cflags --libs haptree) \
     && ldd consumer_usr | grep -E "libhaptree\.so\.[0-9.]+ => /" > /dev/null && ./consumer_usr /usr/share/haptree/models/arm.urdf | tail -1) \
    || { echo "consumer against the installed haptree-dev failed"; ok=0; }
  man -w sim_server > /dev/null 2>&1 || [ -e /usr/share/man/man1/sim_server.1.gz ] || { echo "no man page"; ok=0; }
  purge || ok=0
  for p in haptree haptree-dev python3-haptree; do
    dpkg-query -W "$p" > /dev/null 2>&1 && { echo "$p still known to dpkg after the purge"; ok=0; }
  done
  for f in /usr/bin/sim_server /usr/share/haptree /usr/include/haptree /usr/lib/python3/dist-packages/haptree; do
    [ ! -e "$f" ] || { echo "$f left behind"; ok=0; }
  done
  [ $ok = 1 ] || fail "installed packages did not run or did not purge cleanly"
fi
echo "test_install: OK (${SECONDS} s)"
