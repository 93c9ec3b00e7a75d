#!/usr/bin/env bash
# Installs what haptree needs on Debian 12 (as root, or with sudo). Skips apt when all is present.
set -euo pipefail
PKGS=(
  build-essential cmake pkg-config git
  libeigen3-dev libspdlog-dev libcli11-dev nlohmann-json3-dev
  liblcm-dev liblcm-bin libglib2.0-dev          # LCM (pkg-config lcm needs glib)
  gemmi-dev                                     # PDB / mmCIF reading
  liburdfdom-dev                                # URDF models
  libgtest-dev libgmock-dev libbenchmark-dev    # tests and benchmarks
  libmujoco-dev                                 # test-only external oracle
  libsimbody-dev libbullet-dev                  # peer engines for the side-by-side benchmark (optional at build time)
  python3 python3-matplotlib                    # benchmark plots
  iproute2 util-linux nftables                  # network-namespace tests (ip, unshare; nft loss: docs/network_faults.md)
  tao-pegtl-dev                                 # mmCIF reading through gemmi (haptree/molecule)
  python3-dev pybind11-dev python3-pybind11 python3-numpy   # the haptree Python module (python/)
  python3-pytest python3-pandas                 # its tests (CTest label python) and the log reader's frames
  openjdk-17-jdk-headless liblcm-java           # haptree_lcmtypes.jar for lcm-spy (java/)
  libwebsocketpp-dev libasio-dev                # viewer: HTTP + WebSocket (standalone asio)
  chromium python3-websocket                    # viewer browser test: headless chromium over CDP
  python3-mdanalysis                            # DCD trajectories read back by an outside reader (test)
  clang-14 libclang-rt-14-dev                   # libFuzzer targets (scripts/fuzz.sh, docs/fuzzing.md)
  libsodium-dev                                 # authenticated sessions (haptree/bus/auth.*), viewer tokens
  libssl-dev openssl                            # viewer over https/wss; openssl s_client in its TLS test
  doxygen                                       # API reference (CMake target docs; CTest label docs)
)
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
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
