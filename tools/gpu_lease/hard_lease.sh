#!/usr/bin/env bash
# The fourth 15-minute lease (2026-11-29), one call: go on training the shipped bundle (policy/bundles/multitask,
# packed as a run: pack.py --bundle) on fresh episodes weighted to the two families it fails, stack and
# drawer_put (EXTRA episodes of each, seeds 410000-), with EPISODES of each of the other three for rehearsal;
# twice side by side: as it is (`hq`) and with the grasp-cycle count as an input (`hqs`: stage_bins 3,
# policy/stage.py). Each run has a fixed length (the rate is known from the third lease: ~17 steps/s side by
# side), so the data is loaded once; whatever checkpoint a run has when the call nears its end comes back
# (float16 EMA weights), to be exported with the goal query and evaluated here.
# Carry .whl (without mujoco_studio and glfw), .gl and .gpu: texts.npz (texts.py 410000 410450 with the five
# --task) and multitask (pack.py --bundle policy/bundles/multitask).
# A dry run here: PY=.venv/bin/python EPISODES=1 EXTRA=2 STEPS=6 DATAGEN_LIMIT_S=150 CALL_S=400 \
#     DRY=', "batch_size": 8, "num_workers": 0, "val_every": 3, "checkpoint_every": 3' bash tools/gpu_lease/hard_lease.sh
set -u
T0=$(date +%s)
export TASKS="drawer_put stack pick_place drawer_open drawer_close" SEED_OFFSET=410000
export EXTRA_TASKS="drawer_put stack" EXTRA_EPISODES=${EXTRA:-370}
export DATAGEN_LIMIT_S=${DATAGEN_LIMIT_S:-170}
RECIPE="\"config\": \"policy/bundles/multitask\", \"init_from\": \".gpu/multitask\", \"feature_cache\": 0,
        \"lr\": 2e-4, \"warmup_steps\": 300, \"steps\": ${STEPS:-4000}, \"checkpoint_every\": 500 ${DRY:-}"
bash tools/gpu_lease/job.sh "${EPISODES:-80}" "${CALL_S:-560}" \
    hq="{$RECIPE}" \
    hqs="{$RECIPE, \"stage_bins\": 3}"
bash tools/gpu_lease/wait.sh $(( T0 + ${CALL_S:-560} - $(date +%s) ))
