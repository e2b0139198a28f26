#!/bin/sh
# Make a virtual environment in .venv, installing Debian's python3-venv first when the
# machine lacks it (a fresh Debian/Ubuntu has python3 but often not venv/ensurepip).
set -e
PYTHON=${PYTHON:-python3}
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    echo "posecast needs Python >= 3.11, and there is no $PYTHON on this machine:" \
         "install it (Debian/Ubuntu: apt-get install python3 python3-venv)" >&2
    exit 1
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "posecast needs Python >= 3.11, and $PYTHON is $("$PYTHON" -V 2>&1 | cut -d' ' -f2)." \
         "Install a newer one (Ubuntu 22.04: apt-get install python3.11 python3.11-venv)" \
         "and run: make PYTHON=python3.11" >&2
    exit 1
fi
if "$PYTHON" -m venv --help >/dev/null 2>&1 && "$PYTHON" -c "import ensurepip" >/dev/null 2>&1; then
    :
else
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "installing python3-venv (needed for the virtual environment)"
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq python3-venv python3-pip
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
# Headless OpenGL for the viewer: moderngl renders through EGL, with Mesa's software
# rasterizer (llvmpipe) where there is no GPU. Install what is missing (Debian/Ubuntu).
GL_MISSING=""
for pkg in libegl1 libgl1 libgl1-mesa-dri; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" \
        || GL_MISSING="$GL_MISSING $pkg"
done
if [ -n "$GL_MISSING" ]; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""
        [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        echo "installing$GL_MISSING (headless OpenGL for the viewer)"
        $SUDO apt-get update -qq
        $SUDO apt-get install -y -qq $GL_MISSING
    else
        echo "warning: the viewer needs EGL, OpenGL and Mesa's drivers (on Debian/Ubuntu:" \
             "libegl1 libgl1 libgl1-mesa-dri); headless rendering will fail without them"
    fi
fi
