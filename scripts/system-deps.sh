#!/usr/bin/env bash
# Installs the system libraries open3d needs (libusb-1.0, libgomp) when they are missing.
set -euo pipefail
missing=()
have() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
have 'libgomp.so.1' || missing+=(libgomp1)
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "calstation: missing system libraries for open3d: ${missing[*]}; install them with your package manager" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 || { echo "calstation: run as root or install: ${missing[*]}" >&2; exit 1; }
    sudo="sudo"
fi
echo "calstation: installing ${missing[*]} from Debian's packages"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
