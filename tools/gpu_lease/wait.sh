#!/usr/bin/env bash
# On the lent box: wait SECONDS (or until every run, and its export and eval if job.sh started them, is done),
# show progress, copy each run and its eval results to $OUT.
UNTIL=$(( $(date +%s) + $1 ))
export PYTHONPATH=/tmp/site:$PWD
PY=${PY:-python3}
finished() { grep -q "finish.sh ended" "$1" 2>/dev/null; }
done_all() {
    for r in /tmp/runs/*/; do [ -e "$r/DONE" ] || return 1; done
    for f in /tmp/finish_*.log; do [ -e "$f" ] || continue; finished "$f" || return 1; done
}
while [ "$(date +%s)" -lt $UNTIL ] && ! done_all; do sleep 10; done
for r in /tmp/runs/*/; do
    if [ ! -d "$r" ]; then  # a run's directory appears once its data is loaded and its features encoded
        echo "no run directory yet"; for f in /tmp/train_*.log; do tr '\r' '\n' < "$f" | tail -1 | cut -c1-200; done
        break
    fi
    name=$(basename "$r")
    echo "== $name"; tail -1 "$r/metrics.jsonl"
    tr '\r' '\n' < "/tmp/train_$name.log" | tail -2 | cut -c1-300
    $PY tools/gpu_lease/pull.py "$r"
    if [ -e "/tmp/finish_$name.log" ]; then
        tr '\r' '\n' < "/tmp/finish_$name.log" | tail -4 | cut -c1-300
        [ -e "/tmp/eval/$name/results.jsonl" ] && cp "/tmp/eval/$name/results.jsonl" "${OUT:-out/lease}/${name}_results.jsonl"
    fi
done
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
