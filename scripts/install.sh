#!/usr/bin/env bash
# Creates ./.venv with everything votesplat_ns needs (idempotent: re-running is cheap).
# torch is pinned to the CPU/CUDA pair that works with torchvision on this platform.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_PINS=${TORCH_PINS:-"torch==2.14.1 torchvision==0.29.1"}

# open3d (imported by ns-export) needs libusb; install it when we can.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "installing libusb-1.0-0 (needed by open3d / ns-export)"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "warning: libusb-1.0-0 is missing and cannot be installed here; ns-export will fail to import open3d" >&2
  fi
fi

stamp=.venv/.votesplat-installed
want=$(cat pyproject.toml scripts/install.sh | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# shellcheck disable=SC2086
.venv/bin/python -m pip install -q $TORCH_PINS -e '.[test,synthetic]'
echo "$want" > "$stamp"
