#!/usr/bin/env bash
# One chunk of RAFT training on the accelerator machine the `device` tool lends: bf16 autocast on the
# GPU, a batch of 16, resumed from the carried checkpoint, stopped and saved after MINUTES of
# training (the renders of the synthetic pool come first, on the machine's 16 cores, and are not
# counted). Prepare .device/ here with train/device_prepare.sh, then run from the repository root
# there (the `run` tool, carry [".device"], timeout_s 600):
#
#     bash train/device_chunk.sh 6 init_weights=models/raft_small.pt mask_hidden=128 ...
#
# Any further arguments are train.flow overrides (conf/train_flow.yaml; the same ones every chunk,
# or the schedule changes). The checkpoint comes back as $OUT/ckpt.pt (and, after the last step of
# the schedule, the weights and their ONNX export): copy it to runs/train_flow_gpu/ckpt.pt here.
# The next chunk, or a CPU run with the same overrides and run_dir=runs/train_flow_gpu device=cpu,
# resumes from it. Real samples need DeepFlow (opencv-contrib), which the device image lacks: keep
# real_fraction at 0 there unless run_dir/pool already holds the real pool. The INT8 copy is calibrated
# on the real frames, which the machine does not carry: write it here (`python -m train.flow export_only=true`).
set -euo pipefail
minutes=${1:?usage: device_chunk.sh MINUTES [train.flow overrides]}
shift
: "${OUT:?OUT: the folder whose files come back (the device machine sets it)}"
python=${PYTHON:-python3}
export PYTHONPATH="$PWD/.device/site${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
run=.device/run
mkdir -p "$run" "$OUT"
status=0
"$python" -m train.flow device=cuda amp=bf16 threads=16 batch_size=16 run_dir="$run" max_minutes="$minutes" \
    out_weights="$run/raft_small.pt" export.onnx="$run/raft_small.onnx" export.int8=false "$@" > "$OUT/train.log" 2>&1 || status=$?
for f in ckpt.pt raft_small.pt raft_small.onnx; do
    if [ -f "$run/$f" ]; then cp "$run/$f" "$OUT/$f"; fi
done
tail -c 2000 "$OUT/train.log" | tr '\r' '\n' | tail -n 8
exit $status
