#!/usr/bin/env bash
# On the lent box: `sudd eval` of a bundle on all cores but one, for at most SECONDS; what finished comes back
# in $OUT/eval (results.jsonl is written episode by episode, so a cut-off run still returns every finished one;
# `sudd eval ... --out DIR` here, on a copy of that DIR, finishes the rest and writes the tables).
# usage: bash tools/gpu_lease/eval.sh BUNDLE EPISODES SEED_OFFSET SECONDS [more sudd eval flags]
# Carry .whl (without mujoco_studio, which the eval never imports: it keeps the transfer under 64 MiB), .gl and
# the bundle's git-ignored text encoder (BUNDLE/text_encoder.onnx, BUNDLE/tokenizer).
set -u
B=$1; N=$2; S=$3; LEFT=$4; shift 4
# the cores before OMP_NUM_THREADS is set: GNU nproc reports that variable when it is set (1 on the first lease)
W=${WORKERS:-$(( $(nproc) - 1 ))}
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl OMP_NUM_THREADS=1
PY=${PY:-python3}  # a dry run here: PY=.venv/bin/python (no GPU: the set-up below is skipped)
if command -v nvidia-smi >/dev/null; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
    for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    nvidia-smi -L; nproc
fi
OUTDIR=${OUT:-out/lease}/eval
$PY -c "import mujoco, onnxruntime, tokenizers; print('mujoco', mujoco.__version__, 'onnxruntime', onnxruntime.__version__)" \
    || exit 4
timeout -s INT "$LEFT" $PY -c "import sys; from runtime.cli import main; sys.exit(main(sys.argv[1:]))" eval \
    --policy "$B" --task pick_place --episodes "$N" --seed-offset "$S" --no-collector --workers "$W" --out "$OUTDIR" \
    "$@" 2>&1 | tr '\r' '\n' | grep -v '^$' | awk 'NR % 20 == 0 || /Error|error|success/' | tail -40
echo "finished episodes: $(wc -l < "$OUTDIR/results.jsonl")"
