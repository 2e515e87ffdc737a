#!/bin/sh
# Install a headless-capable Chromium for the viewer's browser test (tests/test_viewer*.py).
# Debian/Ubuntu: the distribution's chromium package; needs root (or sudo). Safe to run twice.
# Elsewhere, install Chromium or Chrome yourself, or point RMAVATAR_CHROMIUM at the binary;
# without one the browser test is skipped with a message saying so.
set -eu

for name in chromium chromium-browser google-chrome google-chrome-stable; do
    if command -v "$name" >/dev/null 2>&1; then
        echo "install-browser: $(command -v "$name") is already installed"
        exit 0
    fi
done

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-browser: no apt-get here; install Chromium with your package manager" >&2
    echo "install-browser: (or set RMAVATAR_CHROMIUM=/path/to/chrome); the viewer browser test will be skipped" >&2
    exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        SUDO="sudo -n"
    else
        echo "install-browser: need root (or password-less sudo) to apt-get install chromium; the viewer browser test will be skipped" >&2
        exit 0
    fi
fi

$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium
command -v chromium
