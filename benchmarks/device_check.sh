#!/usr/bin/env bash
# The checks that need the accelerator machine (one GPU, 16 cores), in under 10 minutes (each Ray start there takes 22-28 s):
#   1. the learner's samples per second on the GPU, at batch sizes from 32 to 2048;
#   2. sampling env steps/s with 1 and 14 rollout actors, the learner idle;
#   3. the whole path on configs/setting1.yaml (its teacher included) with 14 rollout actors and the
#      GPU learner, with its account of every second (benchmarks/where_time_goes.py);
#   4. the same on configs/reward_only/setting4.yaml: the env steps/s that say how far 30 minutes of
#      the accelerator take the reward-only recipe (issue 41's aim there).
# The same code path as on a CPU: only resources.num_gpus_per_learner and the actors change.
#
# Here, first: bash benchmarks/device_bundle.sh (Ray and the other packages that machine lacks).
# Then move policies/ out of the tree (tracked files travel too, and with the policies and the bundle a
# call would carry 74 MB, over its 64 MiB), and with the device tool: run command
# "bash benchmarks/device_check.sh", carry [".bundle"], timeout_s 590; then move policies/ back. Each step prints its figures as it ends; a step that overruns its share is cut, not the rest.
set -uo pipefail
cd "$(dirname "$0")/.."
. benchmarks/device_env.sh
$PY -c "import torch, ray; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'ray', ray.__version__)"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null; echo "$CORES cores"
GPU_PATH=(--cores "$CORES" --set resources.num_rollout_actors=14 --set resources.cpus_per_rollout_actor=1
          --set resources.num_gpus_per_learner=1)

echo "== 1. the learner on the GPU (benchmarks/learner_samples.py)"
timeout 60 $PY benchmarks/learner_samples.py configs/setting1.yaml --gpu --batches 32,128,512,2048 --updates 20
echo "== 2. sampling alone (benchmarks/train_throughput.py --sampling)"
timeout 140 $PY benchmarks/train_throughput.py --sampling 1,14 --seconds 10 --warmup 500
echo "== 3. the whole path: configs/setting1.yaml, 14 rollout actors, the GPU learner (benchmarks/where_time_goes.py)"
timeout 220 $PY benchmarks/where_time_goes.py configs/setting1.yaml --env-steps 4000 "${GPU_PATH[@]}"
echo "== 4. the same on configs/reward_only/setting4.yaml"
timeout 150 $PY benchmarks/where_time_goes.py configs/reward_only/setting4.yaml --env-steps 4000 "${GPU_PATH[@]}"
