#!/usr/bin/env bash
# Call 1 of the second 15-minute lease (2026-11-27): the five-family recipe (famfz_w2's config, the frozen
# encoders of out/run_prefam3) trained there on EPISODES episodes of each family generated there, twice side by
# side: with famfz_w2's denoiser (64-128-256, 4.7 M: its weights come back in float16 to export and evaluate
# here) and with the 70 M denoiser of the first lease; both exported and evaluated there on seeds 100000-...
# of every family, as famfz_w2 was here. Call 2, within 30 s of this one's end: `bash tools/gpu_lease/wait.sh S`.
# Carry .whl, .gl and .gpu: texts.npz (texts.py 1000 1400 with the five --task), famfz_w2.json (that run's
# config.json), run_prefam3, text_encoder.onnx.xz and tokenizer/ (pack.py out/run_prefam3).
set -u
T0=$(date +%s)
FAMILIES="drawer_put drawer_open stack drawer_close pick_place"  # datagen runs them in this order: the scarce first
export TASKS=$FAMILIES EVAL_TASKS=$FAMILIES
export EVAL_END=$(( T0 + ${EVAL_AT:-780} )) EVAL_EPISODES=${EVAL_EPISODES:-20} EVAL_SEED=100000
export DATAGEN_LIMIT_S=${DATAGEN_LIMIT_S:-200}
RECIPE='"config": "policy/bundles/demo", "base": ".gpu/famfz_w2.json", "init_from": ".gpu/run_prefam3",
        "feature_cache": 0, "lr": 3e-4, "warmup_steps": 300'
bash tools/gpu_lease/job.sh "${EPISODES:-300}" "${TRAIN_S:-500}" \
    famw="{$RECIPE}" \
    famb="{$RECIPE, \"down_dims\": [256, 512, 1024], \"kernel_size\": 5, \"step_embed_dim\": 256}"
bash tools/gpu_lease/wait.sh $(( T0 + ${CALL_S:-565} - $(date +%s) ))
