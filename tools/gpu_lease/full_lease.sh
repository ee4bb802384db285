#!/usr/bin/env bash
# Call 1 of a 15-minute lease (2026-11-27): train the `full` preset, and the shipped recipe with full's denoiser,
# on 1000 pick_place episodes generated there, then export and evaluate both there (a full-size bundle is
# ~150-200 MB and cannot come back). Call 2, within 30 s of this one's end: `bash tools/gpu_lease/wait.sh S`.
# Carry .whl (no glfw, no mujoco_studio), .gl and .gpu: texts.npz (texts.py 1000 2600), run_prefam3 (the
# pretrain run's encoders and aux head, fp16), text_encoder.onnx.xz and tokenizer/ (the demo bundle's
# git-ignored text encoder, which export copies; xz keeps the transfer under 64 MiB).
set -u
T0=$(date +%s)
export EVAL_END=$(( T0 + ${EVAL_AT:-720} )) EVAL_EPISODES=${EVAL_EPISODES:-60} EVAL_SEED=100120
export DATAGEN_LIMIT_S=${DATAGEN_LIMIT_S:-170}
bash tools/gpu_lease/job.sh "${EPISODES:-1000}" "${TRAIN_S:-470}" \
    full='{"config": "policy/configs/full_pick_place.toml", "batch_size": 128, "lr": 2e-4, "warmup_steps": 300}' \
    big='{"init_from": ".gpu/run_prefam3", "down_dims": [256, 512, 1024], "kernel_size": 5, "step_embed_dim": 256,
          "aux_condition": true, "freeze_pretrained": true, "obs_horizon": 1, "objective": "flow",
          "inference_steps": 2, "aux_grasp_axis": true, "aux_release_frame": "base", "action_frame": "tcp",
          "aux_target_frame": "tcp", "lr": 3e-4, "warmup_steps": 300}'
bash tools/gpu_lease/wait.sh $(( T0 + ${CALL_S:-565} - $(date +%s) ))
