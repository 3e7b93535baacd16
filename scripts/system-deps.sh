#!/usr/bin/env bash
# Install the system programs telerig uses: Mosquitto (the embedded broker and the
# test broker), OSMesa (headless MuJoCo rendering without a GPU), libusb (pyrealsense2 loads it) and
# espeak-ng (spoken feedback of voice commands).
# Usage: scripts/system-deps.sh [--test]   (--test adds what only the test suite needs: Chromium
# for the browser tests of the WebXR page, the PostgreSQL server for the index tests; the tests
# start their own cluster on 127.0.0.1 in a temp dir and stop it)
set -euo pipefail
pkgs=()
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || pkgs+=(mosquitto)
ldconfig -p 2>/dev/null | grep -q libOSMesa.so || pkgs+=(libosmesa6)
ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || pkgs+=(libgl1)
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || pkgs+=(libusb-1.0-0)
# espeak-ng: spoken feedback of voice commands (telerig.voice); the voice tests synthesize speech with it.
command -v espeak-ng >/dev/null 2>&1 || pkgs+=(espeak-ng)
command -v npm >/dev/null 2>&1 || pkgs+=(npm)  # installs three.js for the operator scene (make scene-js)
if [ "${1:-}" = "--test" ]; then
  [ -x /usr/bin/chromium ] || pkgs+=(chromium)
  ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || pkgs+=(postgresql)
fi
[ ${#pkgs[@]} -eq 0 ] && exit 0
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system packages: ${pkgs[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${pkgs[@]}" >/dev/null
elif command -v brew >/dev/null 2>&1; then
  brew install mosquitto libusb espeak-ng
  if [ "${1:-}" = "--test" ]; then brew install postgresql@16; fi
else
  echo "please install: ${pkgs[*]} (Mosquitto broker, OSMesa, libusb, espeak-ng; PostgreSQL server for tests)" >&2
  exit 1
fi
