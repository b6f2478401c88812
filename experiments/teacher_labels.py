"""What the teacher's labels look like: play episodes by following them, count outcomes and labels,
and compare with a random policy on the same held-out scenarios.

    .venv/bin/python experiments/teacher_labels.py --setting 1 --episodes 40
    .venv/bin/python experiments/teacher_labels.py --config configs/small.yaml --episodes 40
    .venv/bin/python experiments/teacher_labels.py --setting 2 --episodes 40 --tolerant-formation
"""

from __future__ import annotations

import argparse
import collections

import numpy as np

from formation.config import GameConfig
from formation.evaluate import play_greedy
from formation.game import BatchedGame
from formation.learn.config import RunConfig
from formation.learn.teacher import Teacher


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", type=int, default=1)
    parser.add_argument("--config", help="a training config: its game and teacher settings")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--tolerant-formation", action="store_true", help="with --setting: train.tolerant_formation")
    args = parser.parse_args()
    if args.config:
        run = RunConfig.load(args.config)
        config = run.game
        teacher = Teacher.of_run(run)
        eval_seed = run.eval.seed
    else:
        config = GameConfig.from_setting(args.setting, obs_type="grid")
        teacher = Teacher(config, 6, order="lockstep", robust_first_step=True,
                          tolerant_formation=args.tolerant_formation)
        eval_seed = RunConfig.load("configs/quickstart.yaml").eval.seed
    game = BatchedGame(config, batch_size=1)
    labels, wins, steps = collections.Counter(), 0, 0
    for seed in range(args.episodes):
        game.reset(seed=seed)
        while not game.done[0]:
            label = teacher.label(game.scenario(0), first_step=game.steps[0] == 0)
            labels[label] += 1
            game.step(np.array([label if label is not None else (3,) * game.n_agents]))
        wins += bool(game.success[0])
        steps += int(game.steps[0])
    total = sum(labels.values())
    print(f"teacher: {wins}/{args.episodes} successes, {steps / args.episodes:.1f} steps per episode")
    print("labels:", ", ".join(f"{joint}: {n / total:.1%}" for joint, n in labels.most_common()))
    rng = np.random.default_rng(0)
    agents = 1 + config.n_followers
    random = play_greedy(config, lambda obs: rng.integers(0, 4, size=(len(obs), agents)), 1000, eval_seed)
    print(f"random policy: {random['summary']['success']:.1%} success on 1000 held-out scenarios")


if __name__ == "__main__":
    main()
