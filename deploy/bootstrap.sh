#!/bin/sh
# Make a virtual environment in .venv, installing Debian's python3-venv first when the
# machine lacks it (a fresh Debian/Ubuntu has python3 but often not venv/ensurepip).
set -e
if python3 -m venv --help >/dev/null 2>&1 && python3 -c "import ensurepip" >/dev/null 2>&1; then
    :
else
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    echo "installing python3-venv (needed for the virtual environment)"
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq python3-venv python3-pip
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
