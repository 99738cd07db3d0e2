#!/usr/bin/env bash
# Installs what relfusion needs on a fresh Debian 12 machine, idempotently:
#  - Mesa's lavapipe Vulkan driver, so wgpu runs without a GPU (adapter "llvmpipe");
#  - the ONNX Runtime shared library (1.31.1, matching ort's `api-31` feature), taken from the
#    PyPI `onnxruntime` wheel because ort's own download feature cannot work offline.
#  - with --test: Debian's Chromium and chromedriver, for the viewer's browser tests, and
#    kubernetes-validate (PyPI, with the Kubernetes API schemas) for the deploy files' test,
#    and s3s-fs (crates.io), the S3-compatible server of the object-store tests.
# Prints the `export` lines the Makefile evaluates. Needs root or sudo for the apt part only.
set -euo pipefail

packages=(mesa-vulkan-drivers libvulkan1 python3 python3-pip ca-certificates)
if [ "${1:-}" = "--test" ]; then
  packages+=(chromium chromium-driver)
fi

ORT_VERSION=1.31.1
RELFUSION_HOME="${RELFUSION_HOME:-${XDG_CACHE_HOME:-$HOME/.cache}/relfusion}"
ORT_DIR="$RELFUSION_HOME/onnxruntime-$ORT_VERSION"
ORT_LIB="$ORT_DIR/onnxruntime/capi/libonnxruntime.so.$ORT_VERSION"

log() { echo "setup: $*" >&2; }

as_root() {
  if [ "$(id -u)" -eq 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
    log "need root (or sudo) to run: $*"; exit 1; fi
}

missing=()
for pkg in "${packages[@]}"; do
  case "$pkg" in
    python3|python3-pip)
      # Any working python3 with pip will do (a pyenv one counts): only fetch Debian's if none.
      python3 -m pip --version >/dev/null 2>&1 || missing+=("$pkg") ;;
    *) dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg") ;;
  esac
done
if [ ${#missing[@]} -gt 0 ]; then
  log "installing Debian packages: ${missing[*]}"
  as_root apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >&2
fi

if ! command -v cargo >/dev/null; then
  log "cargo not found: install the Rust toolchain (rustup) first"; exit 1
fi

if [ ! -f "$ORT_LIB" ]; then
  log "installing ONNX Runtime $ORT_VERSION into $ORT_DIR"
  tmp=$(mktemp -d)
  trap 'rm -rf "$tmp"' EXIT
  # `pip download` + unzip works under PEP 668 (no environment is modified).
  python3 -m pip download -q --no-deps --only-binary=:all: -d "$tmp" "onnxruntime==$ORT_VERSION" >&2
  mkdir -p "$ORT_DIR.partial"
  python3 -m zipfile -e "$tmp"/onnxruntime-*.whl "$ORT_DIR.partial"
  rm -rf "$ORT_DIR" && mv "$ORT_DIR.partial" "$ORT_DIR"
fi
[ -f "$ORT_LIB" ] || { log "ONNX Runtime library missing after install: $ORT_LIB"; exit 1; }

echo "export ORT_DYLIB_PATH=$ORT_LIB"

if [ "${1:-}" = "--test" ]; then
  KV_VERSION=1.37.0
  PYDEPS="$RELFUSION_HOME/pydeps-kubernetes-validate-$KV_VERSION"
  if [ ! -d "$PYDEPS" ]; then
    log "installing kubernetes-validate $KV_VERSION into $PYDEPS"
    rm -rf "$PYDEPS.partial"
    # --target leaves every Python environment as it is (PEP 668 allows it with the flag).
    python3 -m pip install -q --target "$PYDEPS.partial" --break-system-packages \
      "kubernetes-validate==$KV_VERSION" >&2
    mv "$PYDEPS.partial" "$PYDEPS"
  fi
  echo "export RELFUSION_PYDEPS=$PYDEPS"
  # What users of the robotics ecosystem run (issue 38), for the tests that play them: the
  # `mcap` package with its protobuf decoder and `websockets` read recordings and the live
  # Foxglove protocol; flit_core builds the Python SDK's wheel (python/) offline, and httpx,
  # numpy, trimesh and pytest run its tests; eclipse-zenoh and pycdr2 play a ROS 2 robot on
  # rmw_zenoh (the same Zenoh as the server, a CDR codec of its own), and mcap-ros2-support
  # reads the ROS 2 (CDR) recordings as `ros2 bag` would.
  CLIENT_PYDEPS="$RELFUSION_HOME/pydeps-clients-3"
  if [ ! -d "$CLIENT_PYDEPS" ]; then
    log "installing the Python packages of the client tests into $CLIENT_PYDEPS"
    rm -rf "$CLIENT_PYDEPS.partial"
    python3 -m pip install -q --target "$CLIENT_PYDEPS.partial" --break-system-packages \
      "mcap==1.6.0" "mcap-protobuf-support==0.6.0" "protobuf==7.36.2" "websockets==17.4" \
      "flit_core==4.2.0" "httpx==0.28.1" "numpy==2.4.6" "trimesh==5.2.0" "pytest==9.2.0" \
      "eclipse-zenoh==1.10.2" "pycdr2==1.0.0" "mcap-ros2-support==0.6.0" >&2
    mv "$CLIENT_PYDEPS.partial" "$CLIENT_PYDEPS"
  fi
  echo "export RELFUSION_CLIENT_PYDEPS=$CLIENT_PYDEPS"
  # A real S3-compatible server for the object-store tests: s3s-fs from crates.io (0.14.1, the
  # newest that builds with this toolchain), compiled once into the cache. At opt-level 0: the
  # tests store a few small objects in it, and it compiles in 66 s instead of 161 s on a fresh
  # 2-core machine, where it is part of every cold `make test` (docs/build-time.md).
  S3S_VERSION=0.14.1
  S3S_ROOT="$RELFUSION_HOME/s3s-fs-$S3S_VERSION"
  if [ ! -x "$S3S_ROOT/bin/s3s-fs" ]; then
    log "installing s3s-fs $S3S_VERSION into $S3S_ROOT"
    rm -rf "$S3S_ROOT.partial"
    # In a temporary target folder: its opt-level-0 release artifacts stay out of the project's.
    env -u CARGO_TARGET_DIR CARGO_PROFILE_RELEASE_OPT_LEVEL=0 CARGO_PROFILE_RELEASE_DEBUG=0 \
      cargo install s3s-fs --version "$S3S_VERSION" --locked --features binary \
      --root "$S3S_ROOT.partial" >&2
    rm -rf "$S3S_ROOT" && mv "$S3S_ROOT.partial" "$S3S_ROOT"
  fi
  echo "export RELFUSION_S3S_FS=$S3S_ROOT/bin/s3s-fs"
fi
