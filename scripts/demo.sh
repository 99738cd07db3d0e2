#!/usr/bin/env bash
# The demo job behind `make demo`: the service's own demo. Everything lands in $DEMO_OUT.
#
# 1. starts `relfusiond` (release build) on a free loopback port. With the shared data it
#    uses FastDepth, a metric depth network, and the DSO-class front end (`[pipeline]
#    frontend`), which together give the most accurate trajectory of the measured
#    combinations, in metres (docs/tuning.md, issue 39); without FastDepth, the PyDNet++
#    stand-in with the default front end;
# 2. streams a sequence through it with the client (`relfusion stream`): the shared 7-Scenes
#    redkitchen frames when ../shared/data is present, else a freshly synthesised room;
# 3. fetches the trajectory, the keyframes, the point cloud and the fused mesh (PLY, GLB)
#    into $DEMO_OUT/result/;
# 4. prints what was produced and its ATE against the ground truth, then stops the server
#    gracefully.
set -euo pipefail
out="${DEMO_OUT:-out/demo}"
bindir="${CARGO_TARGET_DIR:-target}/release"
data="${RELFUSION_DATA:-../shared/data}"
fastdepth="$data/models/fastdepth_nyu/fastdepth_224x224_op13.onnx"
model="$data/models/pydnet_pp_matterport/pydnet_pp_matterport_448x640_nchw_fp32.onnx"
sequence="$data/sequences/7scenes_redkitchen_f0000-0299"
mkdir -p "$out"

echo "== gpu" >&2
"$bindir/relfusion" gpu-info | tee "$out/gpu.json"

if [ ! -f "$sequence/rgb.txt" ]; then
  sequence="$out/synth"
  echo "== no shared data: synthesising a 300-frame sequence into $sequence" >&2
  "$bindir/relfusion" synth --out "$sequence" --frames 300 --seed 1 | tee "$out/synth.json"
fi

# The server's default depth model comes from its config / environment (RELFUSIOND_MODEL),
# the front end from its config (an operator's setting).
frontend=lsd
if [ -f "$fastdepth" ]; then model="$fastdepth"; frontend=dso; fi
if [ -f "$model" ]; then export RELFUSIOND_MODEL="$model"; else unset RELFUSIOND_MODEL; fi
printf '[pipeline]\nfrontend = "%s"\n' "$frontend" >"$out/relfusiond.toml"
echo "== starting relfusiond (model: ${RELFUSIOND_MODEL:-none}, front end: $frontend)" >&2
coproc SERVER { exec "$bindir/relfusiond" --config "$out/relfusiond.toml" --listen 127.0.0.1:0 --data-dir "$out/server-data" 2>"$out/relfusiond.log"; }
server_pid=$SERVER_PID
trap 'kill -TERM $server_pid 2>/dev/null || true' EXIT
read -r line <&"${SERVER[0]}"
url="http://${line#listening on }"
echo "== relfusiond is listening at $url" >&2

echo "== streaming $sequence through the service" >&2
"$bindir/relfusion" stream "$sequence" --server "$url" --wait >"$out/stream.jsonl"
session=$(head -n1 "$out/stream.jsonl" | sed -E 's/.*"session": *"([^"]+)".*/\1/')
tail -n1 "$out/stream.jsonl" >&2

echo "== fetching session $session into $out/result" >&2
"$bindir/relfusion" fetch "$session" --server "$url" --out "$out/result"

# "metric" when the depth network's metres anchor the map: the trajectory is in metres, so
# its ATE after a rigid alignment (no scale) is printed too.
scale=$(tail -n1 "$out/stream.jsonl" | sed -nE 's/.*"scale": *"([a-z]+)".*/\1/p')
echo "== scale of the map: ${scale:-unknown}" >&2

echo "== trajectory accuracy (ATE, Sim(3)-aligned) of every frame and of the keyframes" >&2
"$bindir/relfusion" eval traj --gt "$sequence/groundtruth.txt" --est "$out/result/trajectory.txt" | tee "$out/ate_trajectory.json"
"$bindir/relfusion" eval traj --gt "$sequence/groundtruth.txt" --est "$out/result/keyframes.txt" | tee "$out/ate_keyframes.json"

if [ "$scale" = metric ]; then
  echo "== the same in metres (ATE, SE(3)-aligned: no scale fitted)" >&2
  "$bindir/relfusion" eval traj --align se3 --gt "$sequence/groundtruth.txt" --est "$out/result/trajectory.txt" | tee "$out/ate_trajectory_se3.json"
fi

kill -TERM "$server_pid"
wait "$server_pid" || true
trap - EXIT
echo "== demo output in $out" >&2
ls -l "$out" "$out/result" >&2
