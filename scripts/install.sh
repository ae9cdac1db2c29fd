#!/usr/bin/env bash
# Installs everything the project needs on a fresh Debian machine: system GL libraries,
# a virtual environment in .venv, the CPU build of torch and the project itself.
# Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

# System libraries: Mesa EGL for offscreen rendering, OSMesa for the fallback path.
need_apt=()
ldconfig -p | grep -q 'libEGL.so.1' || need_apt+=(libegl1)
ldconfig -p | grep -q 'libEGL_mesa.so.0' || need_apt+=(libegl-mesa0)
ldconfig -p | grep -q 'libGL.so.1' || need_apt+=(libgl1)
[ -e /usr/share/glvnd/egl_vendor.d/50_mesa.json ] || need_apt+=(libegl-mesa0)
ldconfig -p | grep -q 'libOSMesa.so' || need_apt+=(libosmesa6)
ldconfig -p | grep -q 'libgbm.so.1' || need_apt+=(libgbm1)
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "install: apt packages ${need_apt[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
VPY=.venv/bin/python
stamp=.venv/.installed-$(cat pyproject.toml scripts/install.sh | sha1sum | cut -c1-12)
if [ ! -e "$stamp" ]; then
  $VPY -m pip install -q --upgrade pip
  # torch first and pinned: the CPU wheel. Nothing below may pull another torch.
  $VPY -m pip install -q torch==2.13.0
  $VPY -m pip install -q -e ".[dev]"
  # pyrender 0.1.45 pins PyOpenGL==3.1.0, but the OSMesa fallback needs PyOpenGL>=3.1.5
  # (pyproject.toml requires it). We override the pin deliberately: pyrender is installed
  # without its dependency list, and pyproject.toml lists its other dependencies itself.
  $VPY -m pip install -q --no-deps pyrender==0.1.45
  $VPY -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
  rm -f .venv/.installed-*; touch "$stamp"
fi
