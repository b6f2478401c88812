"""Game speed: steps per second of one PettingZoo env and of the batched core, and peak memory.

    .venv/bin/python benchmarks/env_speed.py [--seconds 2] [--setting 1]

Random joint actions; finished games are reset (that cost is included). "game-steps/s" counts
one step of one game. Memory is the peak of numpy allocations during a measured run
(tracemalloc, measured in a separate, untimed pass).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np

from formation.config import GameConfig
from formation.env import parallel_env
from formation.game import BatchedGame, Observer


def single_env(setting: int, frame_stack: int, seconds: float) -> float:
    env = parallel_env(setting, frame_stack=frame_stack)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 4, size=(100_000, env.config.n_followers + 1)).tolist()
    names = env.possible_agents
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for _ in range(500):
            env.step(dict(zip(names, actions[steps % 100_000])))
            steps += 1
            if not env.agents:
                env.reset()
    return steps / (time.perf_counter() - start)


def batched(config: GameConfig, batch: int, seconds: float) -> float:
    game = BatchedGame(config, batch_size=batch, seed=0)
    game.reset()
    observer = Observer(game)
    observer.observe(np.ones(batch, bool))
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, size=(64, batch, game.n_agents))
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for i in range(20):
            game.step(actions[i % 64])
            done = game.done
            if done.any():
                game.reset(mask=done)
            observer.observe(done)
            steps += batch
    return steps / (time.perf_counter() - start)


def peak_bytes(fn, *args) -> int:
    tracemalloc.start()
    fn(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--setting", type=int, default=1)
    args = parser.parse_args()
    s = args.setting
    print(f"setting {s}, {args.seconds:g} s per measurement")
    print(f"{'what':44s} {'steps/s':>12s} {'peak MB':>9s}")
    for k in (1, 4):
        rate = single_env(s, k, args.seconds)
        mem = peak_bytes(single_env, s, k, 0.2) / 2**20
        print(f"{f'one PettingZoo env, pixels, frame_stack={k}':44s} {rate:12,.0f} {mem:9.1f}")
    for obs_type in ("pixels", "grid"):
        for k in (1, 4):
            config = GameConfig.from_setting(s, obs_type=obs_type, frame_stack=k)
            for batch in (1, 64, 1024):
                rate = batched(config, batch, args.seconds)
                mem = peak_bytes(batched, config, batch, 0.2) / 2**20
                label = f"batched core, {obs_type}, frame_stack={k}, batch {batch}"
                print(f"{label:44s} {rate:12,.0f} {mem:9.1f}")


if __name__ == "__main__":
    main()
