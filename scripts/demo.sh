#!/usr/bin/env bash
# The demo job behind `make demo`: everything it produces lands in $DEMO_OUT.
# Today it synthesises a textured-room sequence with exact ground truth, reports the GPU the
# pipeline would use, runs the SLAM pipeline on the sequence (poses + semi-dense map), scores
# the trajectory against the ground truth and, when the shared PyDNet++ model is present,
# measures the depth prior on the synthetic frames. It grows with the pipeline (dense layer,
# mesh, the service).
set -euo pipefail
out="${DEMO_OUT:-out/demo}"
bin="${CARGO_TARGET_DIR:-target}/release/relfusion"
model="${RELFUSION_DATA:-../shared/data}/models/pydnet_pp_matterport/pydnet_pp_matterport_448x640_nchw_fp32.onnx"
mkdir -p "$out"

echo "== gpu" >&2
"$bin" gpu-info | tee "$out/gpu.json"
echo "== synthesising a 300-frame sequence into $out/synth" >&2
"$bin" synth --out "$out/synth" --frames 300 --seed 1 | tee "$out/synth.json"
echo "== SLAM on the synthetic sequence" >&2
"$bin" run "$out/synth" --out "$out/run" | tee "$out/run.json"
echo "== trajectory accuracy (ATE, Sim(3)-aligned) of every frame and of the keyframes" >&2
"$bin" eval traj --gt "$out/synth/groundtruth.txt" --est "$out/run/trajectory.txt" | tee "$out/ate_trajectory.json"
"$bin" eval traj --gt "$out/synth/groundtruth.txt" --est "$out/run/keyframes.txt" | tee "$out/ate_keyframes.json"
if [ -f "$model" ]; then
  echo "== depth prior (PyDNet++) on the synthetic frames, eq. (3) alignment to ground truth" >&2
  "$bin" prior --model "$model" "$out/synth" --frames 60 | tee "$out/prior.json"
else
  echo "== no model at $model: skipping the depth-prior evaluation" >&2
fi
echo "== demo output in $out" >&2
ls -l "$out" >&2
