"""Training throughput: this project's actor-replay-learner path against RLlib's stock DQN path.

    .venv/bin/python benchmarks/train_throughput.py [--seconds 60] [--warmup 2000]
    .venv/bin/python benchmarks/train_throughput.py --recipe configs/setting1.yaml [--set train.replay_ratio=0.0625]
    .venv/bin/python benchmarks/train_throughput.py --sampling 1,2,4,8,14 [--seconds 60]

Same game (setting 1, 84x84 pixels, 4 stacked screens), same modules, same replay ratio, same
number of rollout actors; each path runs ``--seconds`` after a warm-up. Prints env steps/s and
learner updates/s of both and their ratio; how sampling alone grows from 1 to 4 rollout actors
(learner idle); and replay bytes per stored env step of both paths. With ``--recipe``, only this
project's path on a training config as it trains (teacher, prioritized replay, its network and replay
ratio; periodic evaluation off), from an untrained network. With ``--sampling``, only sampling alone, with
each of the given numbers of rollout actors.
"""

from __future__ import annotations

import argparse
import os
import time
from collections import deque

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")

import ray  # noqa: E402

from formation.cli import counts, parse_overrides  # noqa: E402
from formation.config import ConfigError  # noqa: E402
from formation.recipe.config import RunConfig  # noqa: E402
from formation.rllib.algorithm import build_algorithm_config  # noqa: E402

BASE = {"game": {"setting": 1, "obs_type": "pixels", "frame_stack": 4},
        # the paper's reward and plain epsilon-greedy on both paths: RLlib's stock DQN has no teacher
        "train": {"shaping": 0.0, "reward_formation_kept": None, "team_reward": False, "prioritized": False,
                  "exploration": "independent", "follower_answers_leader": False,
                  # configs/paper.yaml's network (the figures in docs/BENCHMARKS.md were taken with it)
                  "leader_window": None, "channels": (16, 32, 32), "hidden": 128,
                  "learning_starts": 1000, "replay_ratio": 0.125, "batch_size": 32,
                  "replay_capacity": 20_000, "total_env_steps": 10**9},
        "resources": {"num_rollout_actors": 1, "games_per_actor": 8, "cpus_per_rollout_actor": 0.5},
        "eval": {"every_env_steps": 10**9}}


def run_config(**sections) -> RunConfig:
    values = {k: dict(v) for k, v in BASE.items()}
    for section, changes in sections.items():
        values[section].update(changes)
    return RunConfig.from_dict(values)


def measure(run: RunConfig, seconds: float, warmup_steps: int) -> dict:
    algo = build_algorithm_config(run).build_algo()
    try:
        while algo.counters["env_steps"] < warmup_steps:
            algo.train()
        start, c0 = time.perf_counter(), dict(algo.counters)
        while time.perf_counter() - start < seconds:
            algo.train()
        elapsed = time.perf_counter() - start
        c = algo.counters
        result = {"env_steps_per_s": (c["env_steps"] - c0["env_steps"]) / elapsed,
                  "updates_per_s": (c["updates"] - c0["updates"]) / elapsed,
                  "replay_ratio": (c["updates"] - c0["updates"]) / max(1, c["env_steps"] - c0["env_steps"]),
                  "replay_bytes_per_env_step": replay_bytes_per_step(algo)}
    finally:
        algo.stop()
    return result


def sampling(actor_counts, seconds: float, warmup_steps: int) -> None:
    print("sampling alone (learner idle), formation path:")
    base = None
    for actors in actor_counts:
        r = measure(run_config(train={"replay_ratio": 1e-6},
                               resources={"num_rollout_actors": actors, "cpus_per_rollout_actor": 0.25}),
                    seconds, warmup_steps)
        base = base or r["env_steps_per_s"] / actors
        print(f"  {actors:2d} rollout actor(s): {r['env_steps_per_s']:10.1f} env steps/s "
              f"({r['env_steps_per_s'] / (base * actors):.0%} of linear from the first)", flush=True)


def replay_bytes_per_step(algo) -> float:
    if hasattr(algo, "replays"):  # ours: the frame replay's arrays over the records they can hold
        stats = algo.replay_stats()  # bytes per slot, times slots (records) per agent step
        return float(np.mean([s["replay_bytes_per_record"] * s["replay_added"] / max(1, s["replay_env_steps"])
                              for s in stats]))
    buffer = algo.local_replay_buffer  # RLlib's: numpy data inside the stored episodes
    total = array_bytes(buffer.episodes)
    steps = buffer.get_num_timesteps()
    return total / max(1, steps)


def array_bytes(obj, seen=None) -> int:
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(array_bytes(v, seen) for v in obj.values())
    if isinstance(obj, list | tuple | deque | set):
        return sum(array_bytes(v, seen) for v in obj)
    total = array_bytes(vars(obj), seen) if hasattr(obj, "__dict__") else 0
    for cls in type(obj).__mro__:  # RLlib's episodes keep their data in __slots__
        for name in getattr(cls, "__slots__", ()):
            total += array_bytes(getattr(obj, name, None), seen)
    return total



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--warmup", type=int, default=2000, help="env steps before timing")
    parser.add_argument("--recipe", help="a training config: time only its own path (formation)")
    parser.add_argument("--sampling", metavar="ACTORS", type=counts,
                        help="only sampling alone, with these numbers of rollout actors (comma-separated)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="with --recipe: change a setting of the config, as formation train --set")
    args = parser.parse_args()
    recipe = None
    if args.recipe:
        try:
            recipe = RunConfig.load(args.recipe, {**parse_overrides(args.set), "eval.every_env_steps": 10**9})
        except (ConfigError, OSError) as error:
            parser.exit(2, f"error: --recipe {args.recipe}: {error}\n")
    ray.init(num_cpus=os.cpu_count() or 2, include_dashboard=False, log_to_driver=False)
    try:
        if recipe is not None:
            r = measure(recipe, args.seconds, args.warmup)
            print(f"{args.recipe} {' '.join(args.set)}: {r['env_steps_per_s']:.1f} env steps/s, "
                  f"{r['updates_per_s']:.2f} learner updates/s ({r['replay_ratio']:.4f} per env step), "
                  f"{args.seconds:g} s after {args.warmup} env steps")
            return
        if args.sampling:
            sampling(args.sampling, args.seconds, args.warmup)
            return
        print(f"setting 1, pixels, 4 stacked screens, replay ratio {BASE['train']['replay_ratio']}, "
              f"batch {BASE['train']['batch_size']}, 1 rollout actor x {BASE['resources']['games_per_actor']} games, "
              f"{args.seconds:g} s each")
        ours = measure(run_config(), args.seconds, args.warmup)
        stock = measure(run_config(train={"path": "stock"}), args.seconds, args.warmup)
        print(f"{'path':10s} {'env steps/s':>12s} {'updates/s':>10s} {'ratio':>7s} {'replay B/step':>14s}")
        for name, r in (("formation", ours), ("stock", stock)):
            print(f"{name:10s} {r['env_steps_per_s']:12.1f} {r['updates_per_s']:10.2f} {r['replay_ratio']:7.3f} "
                  f"{r['replay_bytes_per_env_step']:14,.0f}")
        print(f"formation / stock: env steps/s x{ours['env_steps_per_s'] / stock['env_steps_per_s']:.2f}, "
              f"updates/s x{ours['updates_per_s'] / max(stock['updates_per_s'], 1e-9):.2f}")
        sampling((1, 2, 4), args.seconds / 3, args.warmup // 2)
    finally:
        ray.shutdown()


if __name__ == "__main__":
    main()
