"""Cost of a safety head's labels (``teacher.safety_horizon``, ``formation.recipe.teacher.safety_labels``), which a
rollout actor computes for its 16 games on every step.

Run: ``.venv/bin/python benchmarks/safety_labels.py [n_steps]`` (default 20 steps of 16 games per setting).

Prints, per named setting, milliseconds per step of 16 games, on the states of games played with random moves
(forward twice as likely as the others), for 4 and 8 safe steps (``safety_horizon: 4``, the configs', and 8,
the refit's ``horizon``).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from formation.config import GameConfig
from formation.recipe.rollout import GameRollout
from formation.recipe.teacher import safety_labels

BATCH = 16  # games per rollout actor in configs/setting*.yaml
HORIZONS = (4, 8)


def visited(config: GameConfig, n_steps: int) -> list[list]:
    """The states of ``n_steps`` steps of 16 games played with random moves."""
    rollout, rng, out = GameRollout(config, BATCH, seed=1), np.random.default_rng(0), []
    for _ in range(n_steps):
        out.append([rollout.game.scenario(i) for i in range(BATCH)])
        rollout.step(rng.choice([0, 0, 1, 2, 3], size=(BATCH, 1 + config.n_followers)))
    return out


def main(n_steps: int = 20) -> None:
    print(f"{'setting':>7} " + " ".join(f"{f'{h} steps ms':>16}" for h in HORIZONS))
    for setting in (2, 3, 4):
        config = GameConfig.from_setting(setting)
        states = visited(config, n_steps)
        costs = []
        for horizon in HORIZONS:
            start = time.perf_counter()
            for scenarios in states:
                safety_labels(scenarios, config, horizon)
            costs.append((time.perf_counter() - start) * 1e3 / len(states))
        print(f"{setting:>7} " + " ".join(f"{c:>16.1f}" for c in costs), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
