#!/usr/bin/env bash
# Create or reuse the virtual environment and install tidee with everything it needs.
set -euo pipefail
VENV=${1:-.venv}
cd "$(dirname "$0")/.."

# System libraries for PyBullet's EGL renderer (Mesa llvmpipe). Without them the
# simulator falls back to PyBullet's TinyRenderer, so a failure here is not fatal.
need_pkgs=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_pkgs+=("$pkg")
done
if [ ${#need_pkgs[@]} -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "setup: installing ${need_pkgs[*]} (EGL renderer)"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  ($SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_pkgs[@]}") \
    >>"${TMPDIR:-/tmp}/tidee-setup-apt.log" 2>&1 || echo "setup: could not install ${need_pkgs[*]}; the simulator will use the TinyRenderer"
fi

# Debian's chromium, for the viewer's end-to-end browser test (skipped without it); not fatal.
bash scripts/install_chromium.sh || true

if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
# -qq: errors only (pip's warnings about this machine's package index locations are noise here).
"$VENV/bin/python" -m pip install -qq --upgrade pip
# torch first and pinned: an unpinned torch would pull GBs of CUDA wheels.
echo "setup: installing torch 2.13.0 (CPU) and tidee's dependencies into $VENV"
"$VENV/bin/python" -m pip install -qq "torch==2.13.0"
"$VENV/bin/python" -m pip install -qq -e ".[agent,viewer,dev,cluster]"
echo "setup: $VENV ready"
