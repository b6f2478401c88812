#!/usr/bin/env bash
# The checks that need the accelerator machine (one GPU, 16 cores), in under 10 minutes (each Ray start there takes 22-28 s):
#   1. the learner's samples per second on the GPU, at batch sizes from 32 to 2048 (docs/results/scaling.json's
#      learner_gpu);
#   2. each stage alone and the driver's CPU seconds per 1,000 env steps at 1 to 14 rollout actors
#      (benchmarks/scaling.py: the many-actor step of docs/SCALING.md's model);
#   3. the whole path on configs/reward_only/setting4.yaml with 14 rollout actors and the GPU learner, with its
#      account of every second (benchmarks/where_time_goes.py);
#   4. the same with 4 data-parallel CPU learners and 4 replay shards (the many-learner step).
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
echo "== 2. each stage alone, and the driver at 1 to 14 rollout actors (benchmarks/scaling.py)"
timeout 170 $PY benchmarks/scaling.py --seconds 5 --actors 1,4,8,14
echo "== 3. the whole path: configs/reward_only/setting4.yaml, 14 rollout actors, the GPU learner"
timeout 150 $PY benchmarks/where_time_goes.py configs/reward_only/setting4.yaml --env-steps 4000 "${GPU_PATH[@]}"
echo "== 4. the same with 4 CPU learners and 4 replay shards, 12 rollout actors"
timeout 150 $PY benchmarks/where_time_goes.py configs/reward_only/setting4.yaml --env-steps 4000 --cores "$CORES" \
    --set resources.num_rollout_actors=12 --set resources.cpus_per_rollout_actor=1 \
    --set resources.num_learners=4 --set resources.num_replay_shards=4
