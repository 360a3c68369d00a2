#!/usr/bin/env bash
# `make test` while `stress --cpu N` keeps N processes spinning (default 4: twice the two cores
# the suite is measured on), RUNS times in a row (default 1); stops at the first failure.
#   STRESS_CPU=4 RUNS=3 bash scripts/test-stress.sh
# Each run's result and time go to standard output and to out/test-stress.log.
set -uo pipefail
cd "$(dirname "$0")/.."
cpu="${STRESS_CPU:-4}"
runs="${RUNS:-1}"
mkdir -p out
log=out/test-stress.log
stress --cpu "$cpu" --quiet &
load_pid=$!
trap 'kill "$load_pid" 2>/dev/null; wait "$load_pid" 2>/dev/null' EXIT
echo "calstation test-stress: stress --cpu $cpu (pid $load_pid), $runs run(s) of make test on $(nproc) cores" | tee -a "$log"
for i in $(seq 1 "$runs"); do
    start=$(date +%s)
    make --no-print-directory test > "out/test-stress-$i.out" 2>&1
    status=$?
    took=$(( $(date +%s) - start ))
    summary=$(grep -E '^[0-9]+ (passed|failed)|^=+ .*(passed|failed)' "out/test-stress-$i.out" | tail -2 | tr '\n' ' ')
    line="run $i of $runs: $( [ $status -eq 0 ] && echo passed || echo FAILED ) in ${took} s, load $(cut -d' ' -f1-3 /proc/loadavg): $summary"
    echo "$line" | tee -a "$log"
    if [ $status -ne 0 ]; then
        grep -E '^(FAILED|ERROR) ' "out/test-stress-$i.out" | head -20
        exit $status
    fi
done
