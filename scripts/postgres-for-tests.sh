#!/usr/bin/env bash
# Installs Debian's PostgreSQL server binaries for the test suite (the postgres_url fixture of
# tests/conftest.py starts a private, throw-away server from them). Does nothing when they are
# already installed.
set -euo pipefail
ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 && exit 0
command -v apt-get >/dev/null 2>&1 || { echo "calstation: no apt-get to install PostgreSQL" >&2; exit 1; }
sudo=""
if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 || { echo "calstation: run as root to install PostgreSQL" >&2; exit 1; }
    sudo="sudo"
fi
echo "calstation: installing PostgreSQL for the database tests"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq postgresql >/dev/null
