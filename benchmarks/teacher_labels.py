"""Speed of DAgger's teacher (``formation.recipe.teacher.Teacher``), the rollout actors' largest cost.

Run: ``.venv/bin/python benchmarks/teacher_labels.py [n_games]`` (default 32 per setting).

Prints, per named setting, milliseconds per label with the default recipe's teacher (``lockstep``
order, robust first steps, slack 6): on episodes' first steps (the robust label: every velocity
of the two obstacles nearest the leader tried, 16 hypotheses) and on later steps (states along
the planner's path, every third step), labelled one state at a time (``Teacher.label``) and as a
rollout actor does, 16 games at once (``Teacher.labels``: one shortest-path search for the lot).
Each measurement has a teacher of its own, so no label comes from another's cache; the planner's
one-time setup for a board (its move table) is done before the first.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame
from formation.planner import shortest_path
from formation.recipe.teacher import Teacher

BATCH = 16  # games per rollout actor in configs/setting*.yaml


def states(config: GameConfig, n_games: int) -> tuple[list, list]:
    """Start states of games seeded 0..n-1, and states every third step along their shortest paths."""
    game, starts, later = BatchedGame(config, 1), [], []
    for seed in range(n_games):
        game.reset(seed=seed)
        starts.append(game.scenario(0))
        for t, joint in enumerate((shortest_path(starts[-1], config=config) or [])[:-1]):
            game.step(np.array([joint]))
            if t % 3 == 2:
                later.append(game.scenario(0))
    return starts, later


def ms_per_label(config: GameConfig, batch: list, first_step: bool, batched: bool) -> tuple[float, list]:
    teacher = Teacher(config, slack=6, robust_first_step=True)
    start = time.perf_counter()
    if batched:
        labels = []
        for i in range(0, len(batch), BATCH):
            labels += teacher.labels(batch[i:i + BATCH], [first_step] * len(batch[i:i + BATCH]))
    else:
        labels = [teacher.label(s, first_step=first_step) for s in batch]
    return (time.perf_counter() - start) * 1e3 / len(batch), labels


def main(n_games: int = 32) -> None:
    print(f"{'setting':>7} {'steps':>11} {'states':>6} {'one at a time ms':>17} {f'{BATCH} at once ms':>14}")
    for setting in (1, 2, 3, 4):
        config = GameConfig.from_setting(setting)
        starts, later = states(config, n_games)
        # once per process, not per label: what the planner builds for a board at its first search
        Teacher(config, slack=6).labels(starts[:1], [False])
        for name, batch, first in (("first", starts, True), ("later", later, False)):
            alone, labels = ms_per_label(config, batch, first, batched=False)
            together, same = ms_per_label(config, batch, first, batched=True)
            assert labels == same, "batched labels differ from labels made one at a time"
            print(f"{setting:>7} {name:>11} {len(batch):>6} {alone:>17.1f} {together:>14.1f}", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 32)
