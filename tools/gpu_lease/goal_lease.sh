#!/usr/bin/env bash
# Call 1 of the third 15-minute lease (2026-11-28): go on training the goal-clause policy (out/run_goal: the
# CPU's five-family denoiser, text_goal, frozen encoders of out/run_pre_goal_st) on EPISODES fresh episodes of
# each family generated there (seeds 400000-...), twice side by side: with run_goal's own encoders (`ft`) and with
# those of out/run_pre_goal_st2, whose release point while carrying a block is 2 cm closer (`ft2`). Nothing is
# exported there: the weights (5 M parameters, float16) come back to be exported and evaluated here, so the text
# encoder stays behind and run_goal travels whole.
# Call 2, within 30 s of this one's end: `bash tools/gpu_lease/wait.sh S`, S at least 60 s under budget_left_s.
# Carry .whl, .gl and .gpu: texts.npz (texts.py 400000 400300 with the five --task), run_goal and
# run_pre_goal_st2 (pack.py out/run_goal out/run_pre_goal_st2).
set -u
T0=$(date +%s)
export TASKS="drawer_put drawer_open stack drawer_close pick_place" SEED_OFFSET=400000
export DATAGEN_LIMIT_S=${DATAGEN_LIMIT_S:-180}
RECIPE='"config": "policy/bundles/demo", "base": ".gpu/run_goal/config.json", "init_from": ".gpu/run_goal",
        "feature_cache": 0, "lr": 2e-4, "warmup_steps": 300'
bash tools/gpu_lease/job.sh "${EPISODES:-300}" "${TRAIN_S:-700}" \
    ft="{$RECIPE}" \
    ft2="{$RECIPE, \"encoders_from\": \".gpu/run_pre_goal_st2\"}"
bash tools/gpu_lease/wait.sh $(( T0 + ${CALL_S:-570} - $(date +%s) ))
