#!/usr/bin/env bash
# On the lent box: wait SECONDS (or until every run is done), show progress, copy each run to $OUT.
UNTIL=$(( $(date +%s) + $1 ))
export PYTHONPATH=/tmp/site:$PWD
PY=${PY:-python3}
done_all() { for r in /tmp/runs/*/; do [ -e "$r/DONE" ] || return 1; done; }
while [ "$(date +%s)" -lt $UNTIL ] && ! done_all; do sleep 10; done
for r in /tmp/runs/*/; do
    if [ ! -d "$r" ]; then  # a run's directory appears once its data is loaded and its features encoded
        echo "no run directory yet"; for f in /tmp/train_*.log; do tr '\r' '\n' < "$f" | tail -1 | cut -c1-200; done
        break
    fi
    echo "== $(basename "$r")"; tail -1 "$r/metrics.jsonl"
    tr '\r' '\n' < "/tmp/train_$(basename "$r").log" | tail -2 | cut -c1-300
    $PY tools/gpu_lease/pull.py "$r"
done
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
