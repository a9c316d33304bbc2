#!/usr/bin/env bash
# Installs (if needed) and runs the whole test suite on CPU.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The viewer's browser test drives headless Chromium; only the tests need it.
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "installing chromium (the ns-viewer browser test opens the viewer in it)"
    DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
  else
    echo "warning: chromium is missing and cannot be installed here; the ns-viewer browser test will be skipped" >&2
  fi
fi
# The Triton kernels' tests once more under Triton's interpreter, their only run without a GPU (TRITON_INTERPRET
# must be set before triton is imported, hence a second pytest). The vote kernels are the fused losses' only
# (core/vote_fused.py, with the walk helpers of core/vote_kernel.py), all tested in test_vote_fused.py.
# The interpreter takes seconds per pixel a kernel walks, so this pass runs the cases marked ``interpreter``
# (test_vote_fused.py's INTERPRETER_CASES, which says what they cover), not every parametrization. It runs beside
# the suite (which keeps one core busy, not two: 1.0 cores on average on the 2-core development machine), its
# output printed after the suite's; left out when particular test files or tests were named.
interpreter_pid=
for arg in "$@"; do case $arg in tests*|*.py|*::*) interpreter_pid=none ;; esac; done
if [ -z "$interpreter_pid" ]; then
  interpreter_dir=$(mktemp -d)
  # `|| true`: once waited for, the pass is gone and kill fails, which set -e would turn into the script's status
  trap 'kill "$interpreter_pid" 2>/dev/null || true; rm -rf "$interpreter_dir"' EXIT
  TRITON_INTERPRET=1 .venv/bin/python -m pytest "$@" -p no:cacheprovider --basetemp "$interpreter_dir/tmp" \
    -m interpreter tests/test_vote_fused.py >"$interpreter_dir/log" 2>&1 &
  interpreter_pid=$!
fi
# the 15 slowest tests are listed at the end: the suite is meant to stay near ten minutes
status=0
.venv/bin/python -m pytest --durations=15 "$@" || status=$?
if [ "$interpreter_pid" != none ]; then
  interpreter_status=0
  wait "$interpreter_pid" || interpreter_status=$?
  echo "== the Triton kernels' tests under Triton's interpreter (run beside the suite)"
  cat "$interpreter_dir/log"
  [ "$status" != 0 ] || status=$interpreter_status
fi
exit "$status"
