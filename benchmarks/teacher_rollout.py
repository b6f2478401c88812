"""Cost of DAgger's teacher per env step, called as a rollout actor calls it (``formation/rllib/rollout_actor.py``).

Run: ``.venv/bin/python benchmarks/teacher_rollout.py [n_steps] [settings]`` (default: 100 steps of 16 games
in settings 1,3; e.g. ``... 100 1,2,3,4``; under a minute on one core).

Each setting's ``GameRollout`` of 16 games is played by a stand-in for a learner: the first half of the
games follow the teacher's labels (``teacher.demonstrations`` 0.5), the others take the label's leader move
(a random one with probability ``EPSILON``) and the teacher's answer to it for the followers (a random
joint move with probability ``EPSILON``), so the states include episodes' first steps and states off the
shortest path. Every step makes the calls of the setting's config in the rollout actor's order:
``Teacher.labels`` of all the games, ``Teacher.answers`` to every leader move (``answer_every_leader_move``),
then ``safety_labels`` (``safety_horizon: 4``). Prints milliseconds per env step (one game's step) for the
teacher alone, the game's own stepping and one-time setup not counted, as CPU time of this process (less
disturbed than wall time by other work on the machine), and a digest of every output so two versions can be
compared: e.g. the committed version's ``formation`` unpacked with ``git archive HEAD formation | tar -x -C /tmp/old``
and run with ``PYTHONPATH=/tmp/old``.
"""

from __future__ import annotations

import hashlib
import sys
import time

import numpy as np

from formation.config import GameConfig
from formation.recipe.rollout import GameRollout
from formation.recipe.teacher import Teacher, safety_labels

GAMES = 16  # games per rollout actor in configs/setting*.yaml
EPSILON = 0.2
SAFETY_HORIZON = 4  # configs/setting2-4.yaml


def play(setting: int, n_steps: int, seed: int = 0) -> tuple[float, int, str]:
    """CPU seconds spent in the teacher over ``n_steps`` steps of ``GAMES`` games, the number of first
    steps among the states labelled, and a digest of all the teacher's outputs."""
    config = GameConfig.from_setting(setting)
    rollout = GameRollout(config, GAMES, seed=seed)
    teacher = Teacher(config, slack=6, robust_first_step=True)
    rng = np.random.default_rng(seed)
    game, agents, digest = rollout.game, 1 + config.n_followers, hashlib.sha256()
    # once per process, not per step: what the planner builds for a board at its first search
    Teacher(config, slack=6).labels([game.scenario(0)], [False])
    seconds, firsts = 0.0, 0
    for _ in range(n_steps):
        scenarios = [game.scenario(i) for i in range(GAMES)]
        first_steps = list(game.steps == 0)
        start = time.process_time()
        joints = teacher.labels(scenarios, first_steps)
        answers = [teacher.answers(s, j) if j is not None else None for s, j in zip(scenarios, joints)]
        extra = safety_labels(scenarios, config, SAFETY_HORIZON).tolist()
        seconds += time.process_time() - start
        firsts += sum(first_steps)
        digest.update(repr((joints, answers, extra)).encode())
        actions = rng.integers(0, 4, (GAMES, agents))
        for i, (joint, answer) in enumerate(zip(joints, answers)):
            if joint is None:
                continue
            if i < GAMES // 2:
                actions[i] = joint
                continue
            leader = int(rng.integers(4)) if rng.random() < EPSILON else joint[0]
            if answer[leader] is not None and rng.random() >= EPSILON:
                actions[i] = answer[leader]
            actions[i, 0] = leader
        rollout.step(actions)
    return seconds, firsts, digest.hexdigest()[:12]


def main(n_steps: int = 100, settings: tuple[int, ...] = (1, 3)) -> None:
    print(f"{'setting':>7} {'env steps':>9} {'first steps':>11} {'teacher CPU ms/env step':>23} {'digest':>12}")
    for setting in settings:
        seconds, firsts, digest = play(setting, n_steps)
        env_steps = n_steps * GAMES
        print(f"{setting:>7} {env_steps:>9} {firsts:>11} {seconds * 1e3 / env_steps:>23.2f} {digest:>12}", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100,
         tuple(int(s) for s in sys.argv[2].split(",")) if len(sys.argv) > 2 else (1, 3))
