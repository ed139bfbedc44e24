#!/usr/bin/env bash
# open3d needs the system library libusb-1.0 to import. Install it when we can (root + apt), otherwise say what to do.
set -euo pipefail
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing libusb-1.0-0 (needed by open3d)"
  apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  exit 0
fi
echo "pushtorch: open3d needs the system library libusb-1.0 and it is missing." >&2
echo "  Debian/Ubuntu: sudo apt-get install libusb-1.0-0    Fedora: sudo dnf install libusbx    macOS: brew install libusb" >&2
exit 1
