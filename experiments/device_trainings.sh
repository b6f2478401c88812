#!/usr/bin/env bash
# Trainings side by side on the accelerator machine (one GPU, 16 cores), within one call of the device tool:
# each run gets ACTORS rollout actors and the GPU learner (the learner bounds the path there: about 36
# updates/s, docs/BENCHMARKS.md), stops at its budget or, at the deadline, by SIGTERM (its checkpoint saved,
# as --resume expects), and is exported (--half) and packed as $OUT/NAME.tgz: the export, metrics.jsonl, the
# log and the wall time, to evaluate here.
#
#   bash benchmarks/device_bundle.sh; mv policies /tmp/      # here, as for benchmarks/device_check.sh
#   device run, carry [".bundle"], timeout_s 600:
#     bash experiments/device_trainings.sh 530 s3 "configs/reward_only/setting3.yaml" \
#         s3_noshaping "configs/reward_only/setting3.yaml --set train.shaping=0"
#   mv /tmp/policies .; then for each NAME: tar -xzf FILES_AT/NAME.tgz -C RUNS/ and
#     formation evaluate RUNS/NAME.export --episodes 1000 --seed 3000000
#
# Environment: ACTORS (default 7 per run), GPUS (default 1 per run), OUT (default /tmp/device_out).
set -uo pipefail
[ $# -ge 3 ] && [ $(( ($# - 1) % 2 )) -eq 0 ] || { echo "usage: $0 DEADLINE_S NAME \"CONFIG [--set K=V ...]\" [NAME \"...\"]..." >&2; exit 2; }
deadline=$1; shift
cd "$(dirname "$0")/.."
. benchmarks/device_env.sh
OUT=${OUT:-/tmp/device_out} RUNS=$(mktemp -d)
mkdir -p "$OUT"
start=$SECONDS names=() pids=()
while [ $# -gt 0 ]; do
  name=$1 args=$2; shift 2
  # setsid: each run is its own process group, so that SIGTERM reaches its driver and nothing else
  # shellcheck disable=SC2086
  setsid $PY -m formation train $args --out "$RUNS/$name" --set resources.num_rollout_actors="${ACTORS:-7}" \
    --set resources.cpus_per_rollout_actor=1 --set resources.num_gpus_per_learner="${GPUS:-1}" \
    > "$RUNS/$name.log" 2>&1 &
  names+=("$name") pids+=($!)
done
while [ $((SECONDS - start)) -lt "$deadline" ]; do
  running=0
  for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && running=1; done
  [ $running -eq 0 ] && break
  sleep 5
done
for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && kill -TERM "$p"; done
rcs=()
for p in "${pids[@]}"; do wait "$p"; rcs+=($?); done
for i in "${!names[@]}"; do
  name=${names[$i]} run=$RUNS/${names[$i]}
  echo "$name: exit ${rcs[$i]} (130: stopped at the deadline), $((SECONDS - start)) s since the start" > "$run.wall"
  grep -a "env steps" "$run.log" | tail -1 | tr '\r' '\n' | tail -1 >> "$run.wall"
  $PY -m formation export "$run" "$run.export" --half >> "$run.log" 2>&1
  tar -czf "$OUT/$name.tgz" -C "$RUNS" "$name.export" "$name/metrics.jsonl" "$name.log" "$name.wall"
  cat "$run.wall"
done
ls -l "$OUT"
