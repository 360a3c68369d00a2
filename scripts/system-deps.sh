#!/usr/bin/env bash
# Installs the system packages calstation needs when they are missing: the libraries open3d
# needs (libusb-1.0, libgomp) and Debian's chromium, which the browser tests of the web station
# drive through Playwright (Playwright's own browser download is not used). With the argument
# `stress`, also Debian's `stress`, which `make test-stress` loads the machine with.
set -euo pipefail
missing=()
have() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
have 'libgomp.so.1' || missing+=(libgomp1)
[ -x /usr/bin/chromium ] || missing+=(chromium)
for extra in "$@"; do
    case "$extra" in
        stress) command -v stress >/dev/null 2>&1 || missing+=(stress) ;;
        *) echo "calstation: scripts/system-deps.sh does not know '$extra'" >&2; exit 2 ;;
    esac
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "calstation: missing system packages: ${missing[*]}; install them with your package manager" >&2
    exit 1
fi
sudo=""
if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 || { echo "calstation: run as root or install: ${missing[*]}" >&2; exit 1; }
    sudo="sudo"
fi
echo "calstation: installing ${missing[*]} from Debian's packages"
# another apt process (an unattended upgrade, a parallel set-up) may hold the lock for a while
$sudo apt-get -o DPkg::Lock::Timeout=600 update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get -o DPkg::Lock::Timeout=600 install -y -qq \
    --no-install-recommends "${missing[@]}" >/dev/null
