#!/usr/bin/env bash
# Installs what haptree needs on Debian 12 (as root, or with sudo). Skips apt when all is present.
#   scripts/install_deps.sh           what building and running need (scripts/main.sh)
#   scripts/install_deps.sh --tests   that plus what the tests, benchmarks, fuzzing, packaging, the
#                                     Python module and lcm-spy's jar need (scripts/test.sh)
set -euo pipefail
BUILD_RUN=(
  build-essential cmake pkg-config
  libeigen3-dev libspdlog-dev libcli11-dev nlohmann-json3-dev
  liblcm-dev liblcm-bin libglib2.0-dev          # LCM (pkg-config lcm needs glib; lcm-gen)
  gemmi-dev tao-pegtl-dev                       # PDB / mmCIF reading (haptree/molecule)
  liburdfdom-dev                                # URDF models
  libwebsocketpp-dev libasio-dev                # viewer (HTTP + WebSocket) and the inverse3 device (standalone asio)
  libsodium-dev                                 # authenticated sessions (haptree/bus/auth.*), viewer tokens
  libssl-dev                                    # viewer over https/wss (websocketpp's asio TLS, OpenSSL)
)
TESTS=(
  git
  libgtest-dev libgmock-dev libbenchmark-dev    # tests and benchmarks
  libmujoco-dev                                 # test-only external oracle
  libsimbody-dev libbullet-dev                  # peer engines for the side-by-side benchmark (optional at build time)
  python3 python3-matplotlib                    # benchmark plots
  iproute2 util-linux nftables                  # network-namespace tests (ip, unshare; nft loss: docs/network_faults.md)
  python3-dev pybind11-dev python3-pybind11 python3-numpy   # the haptree Python module (python/)
  python3-pytest python3-pandas                 # its tests (CTest label python) and the log reader's frames
  openjdk-17-jdk-headless liblcm-java           # haptree_lcmtypes.jar for lcm-spy (java/)
  chromium python3-websocket                    # viewer browser test: headless chromium over CDP
  python3-mdanalysis                            # DCD trajectories read back by an outside reader (test)
  clang-14 libclang-rt-14-dev                   # libFuzzer targets (scripts/fuzz.sh, docs/fuzzing.md)
  help2man dpkg-dev file                        # man pages and .debs (cpack finds Depends: with file + dpkg-shlibdeps)
  qemu-user                                     # default binaries run as an older CPU (tests/isa)
  openssl                                       # the viewer's TLS test (openssl req, s_client)
  doxygen                                       # API reference (CMake target docs; CTest label docs)
)
PKGS=("${BUILD_RUN[@]}")
case "${1:-}" in
  --tests) PKGS+=("${TESTS[@]}") ;;
  "") ;;
  *) echo "usage: $0 [--tests]" >&2; exit 2 ;;
esac
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep "install ok installed" > /dev/null || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "[haptree] all Debian packages present"
  exit 0
fi
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
echo "[haptree] installing: ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
