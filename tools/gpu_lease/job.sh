#!/usr/bin/env bash
# On the lent box: set up, generate EPISODES episodes of each of TASKS (default pick_place) on all cores, start
# one training per NAME='OVERRIDES_JSON' in its own session, all due SECONDS after this script started; then return.
# usage: bash tools/gpu_lease/job.sh EPISODES SECONDS NAME='{...}' [NAME2='{...}' ...]
# SEED_OFFSET (default 1000): the data's first seed of each task (texts.py must have embedded the same range).
# EXTRA_TASKS, EXTRA_EPISODES: then more of some families (EXTRA_EPISODES each, counting the first EPISODES).
# With EVAL_END (epoch s) set, each run is then exported and evaluated on EVAL_EPISODES seeds from EVAL_SEED of
# each of EVAL_TASKS (default pick_place; finish.sh), the cores shared among the runs.
set -u
N=$1; LEFT=$2; shift 2
T0=$(date +%s)
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl
export PY=${PY:-python3}  # a dry run here: PY=.venv/bin/python (no GPU: the set-up below is skipped)
if command -v nvidia-smi >/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
    for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
    nvidia-smi -L
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
$PY -c "import mujoco, ompl, zarr, torch; print('torch', torch.__version__, torch.cuda.is_available())" || exit 4
# the demo bundle's git-ignored text encoder, which export copies (pack.py --text-encoder: xz keeps the transfer
# under 64 MiB); a lease that exports nothing there leaves it behind
[ -e policy/bundles/demo/text_encoder.onnx ] || [ ! -e .gpu/text_encoder.onnx.xz ] || $PY - <<'PYEOF' || exit 5
import lzma, shutil
with lzma.open(".gpu/text_encoder.onnx.xz") as f, open("policy/bundles/demo/text_encoder.onnx", "wb") as g:
    shutil.copyfileobj(f, g)
shutil.copytree(".gpu/tokenizer", "policy/bundles/demo/tokenizer", dirs_exist_ok=True)
PYEOF
W=$(( $(nproc) - 1 ))
DATAGEN_END=$(( $(date +%s) + ${DATAGEN_LIMIT_S:-330} ))
datagen() {  # datagen EPISODES TASK...: into /tmp/data (a dataset grows: done episodes are skipped), until DATAGEN_END
    local n=$1; shift
    OMP_NUM_THREADS=1 timeout -s INT $(( DATAGEN_END - $(date +%s) )) $PY -c "import sys; from runtime.cli import main; sys.exit(main(sys.argv[1:]))" \
        datagen $(printf -- "--task %s " "$@") --episodes "$n" --seed-offset "${SEED_OFFSET:-1000}" --holdout-color purple --path-noise-cm 3 --out /tmp/data \
        --workers $W \
        2>&1 | tr '\r' '\n' | tail -3
}
datagen "$N" ${TASKS:-pick_place}
# EXTRA_TASKS get EXTRA_EPISODES each in all (the same seeds on: the first N are there already), in the time left
[ -z "${EXTRA_TASKS:-}" ] || [ "$(date +%s)" -ge $DATAGEN_END ] || datagen "$EXTRA_EPISODES" $EXTRA_TASKS
sleep 2
echo "datagen done at $(( $(date +%s) - T0 )) s"
for spec in "$@"; do
    name=${spec%%=*}; ov=${spec#*=}
    setsid nohup $PY tools/gpu_lease/train.py /tmp/data "/tmp/runs/$name" $(( T0 + LEFT )) "$ov" \
        > "/tmp/train_$name.log" 2>&1 < /dev/null &
    echo "started $name: $ov"
    if [ -n "${EVAL_END:-}" ]; then
        setsid nohup bash tools/gpu_lease/finish.sh "$name" "${EVAL_EPISODES:-60}" "${EVAL_SEED:-100120}" "$EVAL_END" \
            $(( (W + 1) / $# )) > "/tmp/finish_$name.log" 2>&1 < /dev/null &
    fi
done
