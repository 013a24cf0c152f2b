#!/usr/bin/env bash
# Fill .device/ (git-ignored) for train/device_chunk.sh, here, before a `device` run call: the
# pure-Python packages the device image lacks (hydra-core, omegaconf, antlr4; its python3 has torch,
# torchvision, OpenCV and the rest) and the checkpoint the chunk resumes, if there is one.
#
#     bash train/device_prepare.sh [RUN_DIR]        # RUN_DIR: default runs/train_flow_gpu
set -euo pipefail
run=${1:-runs/train_flow_gpu}
python=${PYTHON:-python}
rm -rf .device
mkdir -p .device/site .device/run
for module in hydra omegaconf antlr4; do
    src=$("$python" -c "import os, $module; print(os.path.dirname($module.__file__))")
    cp -r "$src" .device/site/
done
find .device/site -name __pycache__ -prune -exec rm -rf {} +
if [ -f "$run/ckpt.pt" ]; then
    cp "$run/ckpt.pt" .device/run/ckpt.pt
    echo "resumes $run/ckpt.pt"
fi
du -sh .device
