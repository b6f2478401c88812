"""Capacity of each stage of the actor-replay-learner path alone, and the driver's cost as rollout actors are added:
the figures docs/SCALING.md's model reads (``experiments/scaling_model.py`` prints its tables).

    .venv/bin/python benchmarks/scaling.py [--seconds 10] [--actors 1,2,4,8] [--json docs/results/scaling.json]

1. **A rollout actor**, on one thread, nothing beside it: env steps/s of ``Collector.collect`` (acting, exploring,
   stepping 16 games; the teacher's labels where the config has a teacher) with untrained networks, for
   configs/reward_only/setting1.yaml and configs/setting1.yaml (the teacher recipe); and the bytes one env step
   pushes to its replay shard (the pickled records).
2. **A replay shard**, on one thread: the env steps/s it inserts (those records), and the records/s it samples in
   batches of train.batch_size (n-step targets, prioritized), with the bytes per sampled record the learner pulls.
3. **A learner** on one CPU thread (``formation.recipe.learn.Learner``: forward, loss, backward, Adam on both
   modules): updates/s at train.batch_size and at half of it (the share of each of two data-parallel learners),
   and the bytes of the weights sent to every rollout actor each train.weights_every_updates updates.
4. **The driver**, on a local Ray of a CPU per actor and two more: its CPU seconds (all its threads) per 1,000 env
   steps with 1, 2, 4 and 8 rollout actors, on configs/smoke.yaml with the settings' requests (16 games, 8 steps
   each) and its learner at the settings' replay ratio. The actors share the machine's cores, so they may be slow;
   the driver's cost per env step is the figure.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import platform
import time
from pathlib import Path

import torch

from formation.recipe.collect import Collector
from formation.recipe.config import RunConfig
from formation.recipe.learn import Learner
from formation.recipe.replay import FrameReplay
from formation.recipe.team import network_specs, replay_frame_shape

REWARD_ONLY, TEACHER = "configs/reward_only/setting1.yaml", "configs/setting1.yaml"


def timed(call, seconds: float) -> tuple[int, float]:
    """Calls of ``call`` until ``seconds`` passed (at least 2), and the seconds they took."""
    calls, started = 0, time.perf_counter()
    while calls < 2 or time.perf_counter() - started < seconds:
        call()
        calls += 1
    return calls, time.perf_counter() - started


def rollout_actor(config: str, seconds: float) -> tuple[dict, list]:
    """Env steps/s of one rollout actor and bytes per env step to its shard; the records it made."""
    run = RunConfig.load(config)
    networks = {m: spec.build().eval() for m, spec in network_specs(run).items()}
    collector, t = Collector(run), run.train
    steps = run.resources.games_per_actor * t.steps_per_sample
    chunks = []

    def collect():
        records, _ = collector.collect(networks, t.steps_per_sample, env_steps=t.epsilon_env_steps)
        chunks.append(records)

    with torch.no_grad():
        collect()  # the planner's one-time setup for the board, where a teacher labels
        chunks.clear()
        calls, took = timed(collect, seconds)
    wire = sum(len(pickle.dumps(c)) for c in chunks) / (calls * steps)
    return {"config": config, "env_steps_per_s": calls * steps / took, "bytes_per_env_step": wire}, chunks


def replay_shard(config: str, chunks: list, seconds: float) -> tuple[dict, FrameReplay]:
    """Env steps/s one shard inserts, records/s it samples (and bytes per sampled record)."""
    run = RunConfig.load(config)
    t = run.train
    replay = FrameReplay(t.replay_capacity, replay_frame_shape(run), 1 + run.game.n_followers, run.game.frame_stack,
                         prioritized=t.prioritized)
    steps = sum(int((~c.terminal).sum()) for c in chunks)  # a record holds every agent's step; terminal: no step
    i = iter(range(10 ** 9))

    def insert():
        replay.add(chunks[next(i) % len(chunks)])

    calls, took = timed(insert, seconds / 2)
    inserted = calls * steps / len(chunks) / took  # env steps of records inserted per second
    batch = replay.sample(t.batch_size, n_step=t.n_step, gamma=t.gamma)
    calls, took = timed(lambda: replay.sample(t.batch_size, n_step=t.n_step, gamma=t.gamma), seconds / 2)
    return {"insert_env_steps_per_s": inserted, "sample_records_per_s": calls * t.batch_size / took,
            "bytes_per_sampled_record": len(pickle.dumps(batch)) / t.batch_size}, replay


def learner(config: str, replay: FrameReplay, seconds: float) -> dict:
    """Updates/s of one learner on one thread at the config's batch and at half of it; the weights' bytes."""
    run = RunConfig.load(config)
    t = run.train
    networks = {m: spec.build() for m, spec in network_specs(run).items()}
    out = {}
    for name, size in (("updates_per_s", t.batch_size), ("updates_per_s_half_batch", t.batch_size // 2)):
        team = Learner(run, networks)
        batches = iter([replay.sample(size, n_step=t.n_step, gamma=t.gamma) for _ in range(8)] * 10 ** 6)
        calls, took = timed(lambda team=team, batches=batches: team.update(next(batches)), seconds / 2)
        out[name] = calls / took
    out["weights_bytes"] = len(pickle.dumps({m: net.state_dict() for m, net in networks.items()}))
    out["weights_every_updates"] = t.weights_every_updates
    out["batch_size"], out["replay_ratio"] = t.batch_size, t.replay_ratio
    return out


def driver(actors: int, seconds: float) -> dict:
    """The driver's CPU seconds per 1,000 env steps, and env steps/s, with ``actors`` rollout actors."""
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load("configs/smoke.yaml", {
        "resources.num_rollout_actors": actors, "resources.cpus_per_rollout_actor": 1.0,
        "resources.games_per_actor": 16, "train.steps_per_sample": 8, "train.learning_starts": 500,
        "train.total_env_steps": 10 ** 9, "eval.every_env_steps": 10 ** 9})
    algo = build_algorithm_config(run).build_algo()
    try:
        while algo.counters["updates"] == 0:  # past learning_starts: the learner's calls are part of the cost
            algo.train()
        steps, cpu, started = algo.counters["env_steps"], time.process_time(), time.perf_counter()
        while time.perf_counter() - started < seconds:
            algo.train()
        took, spent = time.perf_counter() - started, time.process_time() - cpu
        done = algo.counters["env_steps"] - steps
    finally:
        algo.stop()
    return {"actors": actors, "cpu_s_per_1000_env_steps": 1000 * spent / done, "env_steps_per_s": done / took}


def cpu_name() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").is_file() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0, help="seconds each measurement runs (default 10)")
    p.add_argument("--actors", default="1,2,4,8", help="rollout actors of the driver's measurements")
    p.add_argument("--json", type=Path, help="write the figures here (docs/results/scaling.json); its learner_gpu "
                   "figures, measured on a GPU machine (benchmarks/device_check.sh), are kept")
    args = p.parse_args()
    torch.set_num_threads(1)  # one core per stage, as each of the path's processes has
    figures = {"machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "torch": torch.__version__},
               "learner_gpu": json.loads(args.json.read_text())["learner_gpu"]  # measured on a GPU machine
               if args.json and args.json.is_file() else None}

    actor, chunks = rollout_actor(REWARD_ONLY, args.seconds)
    teacher, _ = rollout_actor(TEACHER, args.seconds)
    figures["rollout_actor"] = {"reward_only": actor, "teacher": teacher}
    print(f"rollout actor: {actor['env_steps_per_s']:,.0f} env steps/s ({REWARD_ONLY}), "
          f"{teacher['env_steps_per_s']:,.0f} with the teacher ({TEACHER}); "
          f"{actor['bytes_per_env_step']:,.0f} bytes per env step to its shard", flush=True)

    shard, replay = replay_shard(REWARD_ONLY, chunks, args.seconds)
    figures["replay_shard"] = shard
    print(f"replay shard: inserts {shard['insert_env_steps_per_s']:,.0f} env steps/s, samples "
          f"{shard['sample_records_per_s']:,.0f} records/s ({shard['bytes_per_sampled_record']:,.0f} bytes each)",
          flush=True)

    figures["learner_cpu"] = learn = learner(REWARD_ONLY, replay, args.seconds)
    print(f"learner, one CPU thread: {learn['updates_per_s']:.1f} updates/s at batch {learn['batch_size']}, "
          f"{learn['updates_per_s_half_batch']:.1f} at {learn['batch_size'] // 2}; weights "
          f"{learn['weights_bytes']:,} bytes", flush=True)

    import ray

    counts = [int(a) for a in args.actors.split(",")]
    ray.init(num_cpus=max(counts) + 2, include_dashboard=False, log_to_driver=False)  # the actors, the learner
    try:
        figures["driver"] = []
        for n in counts:
            figures["driver"].append(row := driver(n, args.seconds))
            print(f"driver, {n} rollout actor(s): {row['cpu_s_per_1000_env_steps']:.3f} CPU s per 1,000 env steps "
                  f"({row['env_steps_per_s']:,.0f} env steps/s on this machine)", flush=True)
    finally:
        ray.shutdown()
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
