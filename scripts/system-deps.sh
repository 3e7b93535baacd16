#!/usr/bin/env bash
# Install the system programs telerig uses: Mosquitto (the embedded broker and the
# test broker) and OSMesa (headless MuJoCo rendering without a GPU).
# Usage: scripts/system-deps.sh [--test]   (--test adds what only the test suite needs: Chromium
# for the browser tests of the WebXR page)
set -euo pipefail
pkgs=()
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || pkgs+=(mosquitto)
ldconfig -p 2>/dev/null | grep -q libOSMesa.so || pkgs+=(libosmesa6)
ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || pkgs+=(libgl1)
if [ "${1:-}" = "--test" ]; then
  [ -x /usr/bin/chromium ] || pkgs+=(chromium)
fi
[ ${#pkgs[@]} -eq 0 ] && exit 0
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system packages: ${pkgs[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${pkgs[@]}" >/dev/null
elif command -v brew >/dev/null 2>&1; then
  brew install mosquitto
else
  echo "please install: ${pkgs[*]} (Mosquitto broker, OSMesa)" >&2
  exit 1
fi
