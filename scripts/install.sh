#!/usr/bin/env bash
# Install coworld and everything it needs into ./.venv (idempotent: a second run only checks).
#   - Debian packages for headless MuJoCo rendering (EGL with Mesa's software renderer) and tcmalloc, when missing
#   - a virtual environment with torch 2.13.0 (CPU build unless a torch is already in the venv),
#     the pinned simulator stack and coworld itself in editable mode with its dev extras.
# Environment: PYTHON (interpreter for the venv, default python3), VENV (default .venv),
# TORCH_PIP_ARGS (extra pip arguments for the torch install), APT_LOCK_WAIT (seconds to wait for apt's locks, 600).
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
VENV=${VENV:-.venv}

# 1. Debian packages for EGL rendering (libEGL + Mesa's llvmpipe), and tcmalloc, the memory allocator the coworld
#    command preloads (coworld/allocator.py).
#    Another apt-get or dpkg (an unattended upgrade, a second install) may hold apt's locks: apt-get waits up to
#    APT_LOCK_WAIT seconds (default 600) for dpkg's lock (DPkg::Lock::Timeout); it does not wait for the package
#    lists' lock of `apt-get update` (it stops with "Could not get lock", exit code 100), so apt_get retries that
#    every 5 s for as long.
APT_LOCK_WAIT=${APT_LOCK_WAIT:-600}
apt_get() {
  local lock log waited=0
  log=$(mktemp)
  until DEBIAN_FRONTEND=noninteractive apt-get -qq -o "DPkg::Lock::Timeout=$APT_LOCK_WAIT" "$@" >"$log" 2>&1; do
    if ! grep -q "Could not get lock" "$log" || ((waited >= APT_LOCK_WAIT)); then
      cat "$log" >&2
      rm -f "$log"
      ((waited == 0)) || echo "install: apt-get $1: the lock was still held after $waited s (APT_LOCK_WAIT)" >&2
      return 1
    fi
    if ((waited == 0)); then
      lock=$(sed -n 's/.*Could not get lock \([^ ]*[^ .]\).*/\1/p' "$log" | head -n 1)
      echo "install: another apt-get or dpkg holds $lock; waiting up to $APT_LOCK_WAIT s"
    fi
    sleep 5
    waited=$((waited + 5))
  done
  rm -f "$log"
}

need=()
for pkg in libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libglvnd0 libtcmalloc-minimal4; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if ((${#need[@]})); then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "install: apt-get install ${need[*]} (waiting up to $APT_LOCK_WAIT s for another apt-get or dpkg to finish)"
    apt_get update
    apt_get install -y "${need[@]}"
  else
    echo "install: missing Debian packages for rendering and tcmalloc: ${need[*]} (run: sudo apt-get install ${need[*]})" >&2
    exit 1
  fi
fi

# 2. The virtual environment.
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
pip=("$VENV/bin/python" -m pip -q --disable-pip-version-check)
# A GPU user who installed a CUDA torch into the venv first keeps it; otherwise the CPU build.
if ! "$VENV/bin/python" -c "import torch" >/dev/null 2>&1; then
  echo "install: torch==2.13.0 (CPU build)"
  # TORCH_PIP_ARGS lets a user point pip at another index, e.g. PyTorch's CPU wheel index.
  # shellcheck disable=SC2086
  "${pip[@]}" install "torch==2.13.0" ${TORCH_PIP_ARGS:-} 2>&1 | grep -v "^WARNING: Location" || true
  "$VENV/bin/python" -c "import torch" 2>/dev/null || { echo "install: torch failed to install" >&2; exit 1; }
fi
echo "install: coworld and its pinned dependencies"
"${pip[@]}" install -e ".[dev]" 2>&1 | grep -v "^WARNING: Location" || true
"$VENV/bin/python" -c "import coworld, dm_control, metaworld, h5py" || { echo "install: failed" >&2; exit 1; }
"$VENV/bin/python" -m pip check >/dev/null || { "$VENV/bin/python" -m pip check >&2; exit 1; }
echo "install: done ($("$VENV/bin/coworld" --version))"
