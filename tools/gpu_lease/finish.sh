#!/usr/bin/env bash
# On the lent box, started by job.sh for each run: once the run has written DONE, export it (the text encoder
# copied from the committed demo bundle: the box has no MiniLM package) and `sudd eval` it on WORKERS cores
# until the epoch second EVAL_END. A full-size bundle (~200 MB) cannot come back (16 MiB a file), so its
# figures are what returns: $OUT/<name>_results.jsonl via wait.sh.
# usage: bash tools/gpu_lease/finish.sh NAME EPISODES SEED_OFFSET EVAL_END WORKERS
set -u
trap 'echo "finish.sh ended"' EXIT  # wait.sh's sign that this run has nothing more to come
NAME=$1; N=$2; S=$3; END=$4; W=$5
RUN=/tmp/runs/$NAME; B=/tmp/bundles/$NAME
SUDD=("${PY:-python3}" -c "import sys; from runtime.cli import main; sys.exit(main(sys.argv[1:]))")
while [ ! -e "$RUN/DONE" ] && [ "$(date +%s)" -lt "$END" ]; do
    grep -q Traceback "/tmp/train_$NAME.log" 2>/dev/null && { echo "$NAME: training failed"; exit 1; }
    sleep 5
done
[ -e "$RUN/DONE" ] || { echo "$NAME: not done by the eval deadline"; exit 1; }
OMP_NUM_THREADS=4 "${SUDD[@]}" export "$RUN" --out "$B" --text-encoder-from policy/bundles/demo || exit 2
echo "$NAME exported at $(date +%s)"
OMP_NUM_THREADS=1 timeout -s INT $(( END - $(date +%s) )) "${SUDD[@]}" eval --policy "$B" $(printf -- "--task %s " ${EVAL_TASKS:-pick_place}) \
    --episodes "$N" --seed-offset "$S" --no-collector --workers "$W" --latency-ms 6 --out "/tmp/eval/$NAME" \
    2>&1 | tr '\r' '\n' | grep -v '^$' | tail -5
echo "$NAME: $(wc -l < "/tmp/eval/$NAME/results.jsonl") episodes evaluated"
