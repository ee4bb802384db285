#!/usr/bin/env bash
# Here: turn pulled NAME.pt + NAME.tar pairs into run directories PREFIX<NAME> that `sudd export` reads.
# usage: bash tools/gpu_lease/unpack.sh FILES_DIR PREFIX
set -euo pipefail
for tar in "$1"/*.tar; do
    name=$(basename "$tar" .tar); run="$2$name"
    mkdir -p "$run/checkpoints"; tar xf "$tar" -C "$run"
    if [ -e "$1/$name.pt" ]; then
        step=$(.venv/bin/python -c "import torch; print(torch.load('$1/$name.pt', weights_only=False)['step'])")
        cp "$1/$name.pt" "$run/checkpoints/step_$(printf %08d "$step").pt"
    fi
    echo "$run"
done
