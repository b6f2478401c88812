"""Cost of a safety head's labels (``train.safety_horizon``, ``formation.learn.teacher.safety_labels``), which a
rollout actor computes for its 16 games on every step.

Run: ``.venv/bin/python benchmarks/safety_labels.py [n_steps]`` (default 20 steps of 16 games per setting).

Prints, per named setting, milliseconds per step of 16 games, on the states of games played with random moves
(forward twice as likely as the others): 4 safe steps (``safety_horizon: 4``), and the moves that keep a path
(``safety_horizon: path``) with ``safety_slack`` 0, 1 and 2, searched by the planner (with slack 0 a rollout
actor takes the teacher's own searches instead, at no extra cost).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from formation.config import GameConfig
from formation.learn.rollout import GameRollout
from formation.learn.teacher import safety_labels

BATCH = 16  # games per rollout actor in configs/setting*.yaml
PLANNER_SLACK = 6  # train.planner_slack's default
KINDS = ((4, 0), ("path", 0), ("path", 1), ("path", 2))  # (safety_horizon, safety_slack)
NAMES = ("4 steps", "path, slack 0", "path, slack 1", "path, slack 2")


def visited(config: GameConfig, n_steps: int) -> list[tuple[list, np.ndarray]]:
    """The states (and their episodes' steps) of ``n_steps`` steps of 16 games played with random moves."""
    rollout, rng, out = GameRollout(config, BATCH, seed=1), np.random.default_rng(0), []
    for _ in range(n_steps):
        game = rollout.game
        out.append(([game.scenario(i) for i in range(BATCH)], game.steps.copy()))
        rollout.step(rng.choice([0, 0, 1, 2, 3], size=(BATCH, 1 + config.n_followers)))
    return out


def main(n_steps: int = 20) -> None:
    print(f"{'setting':>7} " + " ".join(f"{name + ' ms':>16}" for name in NAMES))
    for setting in (2, 3, 4):
        config = GameConfig.from_setting(setting)
        states = visited(config, n_steps)
        costs = []
        for horizon, slack in KINDS:
            start = time.perf_counter()
            for scenarios, steps in states:
                safety_labels(scenarios, steps, config, horizon, slack, PLANNER_SLACK)
            costs.append((time.perf_counter() - start) * 1e3 / len(states))
        print(f"{setting:>7} " + " ".join(f"{c:>16.1f}" for c in costs), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
