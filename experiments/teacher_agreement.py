"""Where a trained team goes wrong: play its greedy policy on the run's held-out scenarios and
compare every action with the teacher's label for the same state.

    .venv/bin/python experiments/teacher_agreement.py runs/s1_prio [--episodes 200]

Prints how often each module's action equals the label, which moves replace which labels, and for
every outcome (success, leader or follower collision, formation break, time-out) which agent first
left the teacher's joint action ("leader", "follower", "both", or "never") and at which step.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np
import torch
from ray.rllib.core.rl_module.rl_module import RLModule

from formation.evaluate import play_greedy
from formation.learn.config import RunConfig
from formation.learn.qnet import team_q_values
from formation.learn.rollout_actor import module_of_agent
from formation.learn.teacher import Teacher

MOVE_NAMES = ("F", "FL", "FR", "S")  # the spec's action names, by index


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder of `formation train` (config.yaml, checkpoint/)")
    parser.add_argument("--episodes", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = RunConfig.load_saved(args.run / "config.yaml")
    modules_dir = (args.run / "checkpoint" / "learner_group" / "learner" / "rl_module").resolve()
    names = module_of_agent(run)
    modules = {m: RLModule.from_checkpoint(str(modules_dir / m)) for m in sorted(set(names))}
    teacher = Teacher.of_run(run)
    agree, labelled = collections.Counter(), 0
    confusion = {name: collections.Counter() for name in run.game.agent_names}  # (label, action) when they differ
    first_off: dict[int, tuple[int, str]] = {}

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            q = {m: module.q_network(torch.from_numpy(obs)).numpy() for m, module in modules.items()}
        return team_q_values(q, names).argmax(-1)

    def compare(game, actions: np.ndarray, live: np.ndarray) -> None:
        nonlocal labelled
        for i in np.flatnonzero(live):
            label = teacher.label(game.scenario(i), first_step=game.steps[i] == 0)
            if label is None:
                continue
            labelled += 1
            same = actions[i] == np.asarray(label)
            for agent, name in enumerate(run.game.agent_names):
                agree[name] += bool(same[agent])
                if not same[agent]:
                    confusion[name][(MOVE_NAMES[label[agent]], MOVE_NAMES[actions[i, agent]])] += 1
            agree["team"] += bool(same.all())
            if not same.all() and i not in first_off:
                who = "both" if not same.any() else "leader" if not same[0] else "follower"
                first_off[i] = (int(game.steps[i]), who)

    played = play_greedy(run.game, act, args.episodes, run.eval.seed, watch=compare)
    outcome = {i: ("success" if played["success"][i] else "leader collision" if played["leader_collided"][i]
                   else "follower collision" if played["follower_collided"][i]
                   else "formation break" if played["broken"][i] else "time-out") for i in range(args.episodes)}
    print(f"{labelled} labelled states; the action equals the teacher's label:",
          ", ".join(f"{k} {v / labelled:.1%}" for k, v in agree.items()))
    for name, pairs in confusion.items():
        swaps = ", ".join(f"{label} -> {action}: {n}" for (label, action), n in pairs.most_common())
        print(f"{name}'s departures (label -> action): {swaps}")
    table = collections.defaultdict(list)
    for i, end in outcome.items():
        step, who = first_off.get(i, (None, "never"))
        table[(end, who)].append(step)
    print(f"{'outcome':<20} {'first off the label':<20} {'episodes':>8}  steps of the first departure")
    for (end, who), steps in sorted(table.items()):
        shown = sorted(s for s in steps if s is not None)
        print(f"{end:<20} {who:<20} {len(steps):>8}  {shown if shown else ''}")


if __name__ == "__main__":
    main()
