#!/bin/sh
# Installs the Debian packages facewire needs: Mesa's EGL for offscreen rendering, PortAudio
# for sound (sounddevice) and Python's venv module. With --test, also what the test suite
# uses: iproute2 (network namespaces for the two-host call test), docker-compose (validates
# docker-compose.yml; no Docker engine is needed), chromium (headless, screenshots the live
# view's page) and xvfb (a display for the --window test).
# Does nothing when they are already there.
set -eu
packages="libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgles2 libportaudio2"
[ "${1:-}" = "--test" ] && packages="$packages iproute2 docker-compose chromium xvfb"
need=""
for pkg in $packages; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || need="$need $pkg"
done
python3 -c "import ensurepip, venv" 2>/dev/null || need="$need python3-venv"
[ -z "$need" ] && exit 0
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
echo "installing Debian packages:$need"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends $need
