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
# Install the Debian/Ubuntu packages named that are missing ($1: what they are for).
install_missing() {
    why=$1
    shift
    MISSING=""
    for pkg in "$@"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" \
            || MISSING="$MISSING $pkg"
    done
    [ -n "$MISSING" ] || return 0
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "warning: install$MISSING ($why): this machine has no apt-get" >&2
        return 0
    fi
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "installing$MISSING ($why)"
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq $MISSING
}
# Headless OpenGL for the viewer: moderngl renders through EGL, with Mesa's software
# rasterizer (llvmpipe) where there is no GPU.
install_missing "headless OpenGL for the viewer" libegl1 libgl1 libgl1-mesa-dri
# Node.js and npm build the browser spectator (client/web) at setup; a machine that has
# them already (another distribution's packages, nvm) keeps its own
if ! command -v npm >/dev/null 2>&1; then
    install_missing "Node.js and npm, to build the browser spectator" nodejs npm
fi
# `bootstrap.sh test`: what the test suite needs besides, Chromium for the browser tests
# and a real redis-server for serve --redis
if [ "${1:-}" = "test" ] && ! command -v chromium >/dev/null 2>&1; then
    install_missing "Chromium, for the browser spectator's tests" chromium
fi
if [ "${1:-}" = "test" ] && ! command -v redis-server >/dev/null 2>&1; then
    install_missing "redis-server, for the tests of serve --redis" redis-server
fi
