#!/usr/bin/env bash
# Open3D's wheel links against libusb-1.0; Debian/Ubuntu ship it as libusb-1.0-0.
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
echo "installing system library libusb-1.0-0 (needed by Open3D)"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
