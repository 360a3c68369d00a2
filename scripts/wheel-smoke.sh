#!/usr/bin/env bash
# calstation as a user installs it: the sdist and wheel of calstation and of each plugin built
# (python -m build: each wheel from its sdist) and checked (twine check), installed into a new
# virtual environment outside the checkout (calstation with its `sim` extra), and used from a
# folder that holds no calstation file: --version, a shipped recipe copied and run on the
# simulated station to PASS, history, and serve answering /.
#   bash scripts/wheel-smoke.sh            (make wheel-smoke; .ci/run)
# Needs the development environment (make setup: build, twine) and the package index for the
# new environment's dependencies (pip's cache serves them after the first time).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
dev="$repo/.venv/bin"
python="${PYTHON:-python3}"
work="$(mktemp -d "${TMPDIR:-/tmp}/calstation-wheel-smoke.XXXXXX")"
server=""
cleanup() {
    if [ -n "$server" ]; then kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; fi
    rm -rf "$work"
}
trap cleanup EXIT
say() { printf 'wheel-smoke: %s\n' "$*"; }

dist="$work/dist"
for project in "$repo" "$repo"/plugins/*/; do
    say "building $(basename "$project")"
    "$dev/python" -m build --outdir "$dist" "$project" > "$work/build.log" 2>&1 \
        || { cat "$work/build.log"; exit 1; }
done
"$dev/twine" check --strict "$dist"/* > "$work/twine.log" 2>&1 || { cat "$work/twine.log"; exit 1; }
say "twine check: $(ls "$dist" | wc -l) files pass"

say "installing the wheels into $work/venv"
"$python" -m venv "$work/venv"
bin="$work/venv/bin"
core=("$dist"/calstation-[0-9]*.whl)
{ "$bin/python" -m pip install --upgrade pip \
    && "$bin/python" -m pip install "${core[0]}[sim]" "$dist"/calstation_*.whl; } \
    > "$work/install.log" 2>&1 || { tail -40 "$work/install.log"; exit 1; }

cd "$work"  # nothing of the checkout here: recipes and migrations come from the package
export CALSTATION_HOME="$work/home"
unset CALSTATION_DB_URL CALSTATION_RECIPES CALSTATION_RECORDINGS_URL
"$bin/calstation" --version
"$bin/calstation" recipes list > "$work/list.txt"
grep -q "sim-periodicity.yaml" "$work/list.txt" || { cat "$work/list.txt"; exit 1; }
"$bin/calstation" recipes copy sim-periodicity "$work/station.yaml"
"$bin/calstation" run "$work/station.yaml" --yes > "$work/run.txt" 2>&1 \
    || { tail -40 "$work/run.txt"; exit 1; }
grep -q "PASS" "$work/run.txt" || { tail -40 "$work/run.txt"; exit 1; }
say "simulated run: PASS"
"$bin/calstation" history --json > "$work/history.json"
"$bin/python" - "$work/history.json" <<'EOF'
import json, sys
runs = json.load(open(sys.argv[1]))
runs = runs["runs"] if isinstance(runs, dict) else runs
assert [r["status"] for r in runs] == ["passed"], runs
EOF
say "history: the run, passed"

port="$("$bin/python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
"$bin/calstation" serve --port "$port" > "$work/serve.txt" 2>&1 &
server=$!
"$bin/python" - "$port" "$server" <<'EOF'
import os, sys, time, urllib.request
port, pid = int(sys.argv[1]), int(sys.argv[2])
deadline = time.monotonic() + 120
while True:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
            body = r.read().decode()
        break
    except OSError:
        os.kill(pid, 0)  # the server is still there (ProcessLookupError: it died)
        if time.monotonic() > deadline:
            raise SystemExit("serve did not answer / within 120 s")
        time.sleep(0.5)
assert r.status == 200 and "calstation" in body.lower(), r.status
EOF
say "serve answered / on port $port"
say "OK"
