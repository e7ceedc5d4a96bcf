#!/usr/bin/env bash
# Install (idempotent) and run the test suite. Extra arguments go to pytest.
# By default the suite skips tests marked `slow`; COWORLD_SLOW=1 runs them too. It runs on one worker per core
# (pytest-xdist; `-n 0` among the arguments runs it in one process).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}
marker=(-m "not slow")
[ "${COWORLD_SLOW:-0}" = 1 ] && marker=()
set +e
.venv/bin/python -m pytest -n auto --dist worksteal "${marker[@]}" "$@"
rc=$?
set -e
if [ "$rc" = 5 ]; then
  echo "test: pytest collected no tests; that is a failure" >&2
  exit 1
fi
exit "$rc"
