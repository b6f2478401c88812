"""Does the teacher's label depend on obstacles the leader window does not show?

A state's label is "hidden-dependent" when re-drawing every obstacle outside the window (another
column that the window still does not show, another velocity; 8 tries) changes it: no network
that sees only the window can then be sure of the label.

Without ``--run``: the teacher plays (a random joint move in 10% of the steps, as
``imitation_probe.py collect``) and the share of hidden-dependent states is printed. With
``--run``: a trained team plays the run's held-out scenarios greedily, and each episode's first
departure from the teacher's label is classed by the episode's outcome, whether the state was
hidden-dependent, and whether the team's joint action still left a path (the teacher's slack).

    .venv/bin/python experiments/hidden_obstacles.py --setting 1 --episodes 150 --window 12 3 10
    .venv/bin/python experiments/hidden_obstacles.py --run runs/s1_cells --window 12 3 10
"""

from __future__ import annotations

import argparse
import collections
import dataclasses

import numpy as np

from formation.config import GameConfig
from formation.evaluate import play_greedy
from formation.game import BatchedGame, Scenario
from formation.learn.config import RunConfig
from formation.learn.teacher import Teacher
from formation.policy import load

TRIES = 8


class HiddenProbe:
    """Whether a state's label changes when the obstacles outside the window are re-drawn."""

    def __init__(self, config: GameConfig, teacher: Teacher, window: tuple[int, int, int], seed: int = 0):
        self.config, self.teacher, self.window = config, teacher, window
        self.rng = np.random.default_rng(seed)
        self.velocities = [sign * speed for speed in config.obstacle_speeds for sign in (1, -1)]

    def depends(self, scenario: Scenario, label: tuple[int, ...]) -> bool:
        up, down, side = self.window
        (lr, lc), width = scenario.leader, self.config.width
        rows_seen = range(lr - up, lr + down + 1)
        hidden = [i for i, (r, c, _) in enumerate(scenario.obstacles) if r not in rows_seen or abs(c - lc) > side]
        if not hidden:
            return False
        for _ in range(TRIES):
            obstacles = list(scenario.obstacles)
            for i in hidden:
                r = obstacles[i][0]
                cols = [c for c in range(width) if abs(c - lc) > side] if r in rows_seen else list(range(width))
                obstacles[i] = (r, int(self.rng.choice(cols)), int(self.rng.choice(self.velocities)))
            if self.teacher.label(dataclasses.replace(scenario, obstacles=tuple(obstacles))) != label:
                return True
        return False


def teacher_states(setting: int, episodes: int, window: tuple[int, int, int]) -> None:
    config = GameConfig.from_setting(setting, obs_type="grid")
    teacher = Teacher(config, 6, order="lockstep", robust_first_step=True)
    probe, game, rng = HiddenProbe(config, teacher, window), BatchedGame(config, batch_size=1), np.random.default_rng(1)
    states = dependent = 0
    for episode in range(episodes):
        game.reset(seed=10_000 + episode)
        while not game.done[0]:
            first = bool(game.steps[0] == 0)
            label = teacher.label(game.scenario(0), first_step=first)
            if label is None:
                break
            if not first:  # the first step's label is the robust one, made for an unknown motion
                states += 1
                dependent += probe.depends(game.scenario(0), label)
            joint = label if rng.random() >= 0.1 else tuple(int(a) for a in rng.integers(0, 4, size=game.n_agents))
            game.step(np.array([joint]))
    print(f"setting {setting}, window {window}: {states} states after the first step; the label depends on "
          f"obstacles outside the window in {dependent} ({dependent / states:.2%})")


def first_departures(run_dir: str, episodes: int, window: tuple[int, int, int]) -> None:
    run = RunConfig.load_saved(f"{run_dir}/config.yaml")
    teacher = Teacher.of_run(run)
    probe, policy = HiddenProbe(run.game, teacher, window), load(run_dir)
    departure: dict[int, str] = {}

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        for i in np.flatnonzero(live):
            if i in departure:
                continue
            first, scenario = bool(game.steps[i] == 0), game.scenario(i)
            label = teacher.label(scenario, first_step=first)
            joint = tuple(int(a) for a in actions[i])
            if label is None or joint == label:
                continue
            hidden = "hidden-dependent" if not first and probe.depends(scenario, label) else "visible"
            departure[i] = f"{hidden}, {'a path left' if teacher._opens(scenario, joint) else 'doomed'}"

    played = play_greedy(run.game, policy.act_batch, episodes, run.eval.seed, watch=watch)
    table = collections.Counter((("success" if played["success"][i] else "failure"), departure.get(i, "never"))
                                for i in range(episodes))
    print(f"{run_dir}: {episodes} held-out episodes, window {window}; outcome / first departure from the label")
    for (outcome, where), n in sorted(table.items()):
        print(f"{outcome:<8} {where:<32} {n}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", type=int, default=1)
    parser.add_argument("--episodes", type=int, help="default: 150 teacher episodes, or 200 of the run's")
    parser.add_argument("--window", type=int, nargs=3, default=[12, 3, 10], metavar=("UP", "DOWN", "SIDE"))
    parser.add_argument("--run", help="a run folder: classify its greedy team's first departures instead")
    args = parser.parse_args()
    if args.run:
        first_departures(args.run, args.episodes or 200, tuple(args.window))
    else:
        teacher_states(args.setting, args.episodes or 150, tuple(args.window))


if __name__ == "__main__":
    main()
