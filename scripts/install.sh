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
# torch's CUDA build and its nvidia wheels make the venv ~8.3 GB: say so before pip runs out of space half-way
need_kb=$((9 * 1024 * 1024))
[ -d .venv/lib ] && need_kb=$((1024 * 1024))  # updating an existing venv
free_kb=$(df -Pk . | awk 'NR == 2 {print $4}')
if [ -n "$free_kb" ] && [ "$free_kb" -lt "$need_kb" ]; then
  echo "install.sh: error: $((free_kb / 1024)) MB free on the disk of $PWD; the environment needs ~$((need_kb / 1024 / 1024)) GB free: free some space and run again" >&2
  exit 1
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# shellcheck disable=SC2086
.venv/bin/python -m pip install -q $TORCH_PINS -e '.[test,synthetic]'
echo "$want" > "$stamp"
