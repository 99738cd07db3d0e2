#!/usr/bin/env bash
# The demo job behind `make demo`: everything it produces lands in $DEMO_OUT.
# Today it synthesises a textured-room sequence with exact ground truth, reports the GPU the
# pipeline would use and, when the shared PyDNet++ model is present, measures the depth prior on
# the synthetic frames. It grows with the pipeline (SLAM run, dense layer, mesh, the service).
set -euo pipefail
out="${DEMO_OUT:-out/demo}"
bin="${CARGO_TARGET_DIR:-target}/release/relfusion"
model="${RELFUSION_DATA:-../shared/data}/models/pydnet_pp_matterport/pydnet_pp_matterport_448x640_nchw_fp32.onnx"
mkdir -p "$out"

echo "== gpu" >&2
"$bin" gpu-info | tee "$out/gpu.json"
echo "== synthesising a 300-frame sequence into $out/synth" >&2
"$bin" synth --out "$out/synth" --frames 300 --seed 1 | tee "$out/synth.json"
if [ -f "$model" ]; then
  echo "== depth prior (PyDNet++) on the synthetic frames, eq. (3) alignment to ground truth" >&2
  "$bin" prior --model "$model" "$out/synth" --frames 60 | tee "$out/prior.json"
else
  echo "== no model at $model: skipping the depth-prior evaluation" >&2
fi
echo "== demo output in $out" >&2
ls -l "$out" >&2
