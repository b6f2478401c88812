"""Who leaves the shortest paths first: play a policy greedily as `formation evaluate` does (within the
joint moves its safety heads judge safe, if it has any) and, at every step, compare the team's
joint move with every joint move that starts a shortest path (the planner's
``shortest_first_moves``), not with one label.

    .venv/bin/python experiments/first_mistake.py policies/setting1 [--episodes 300] [--seed 2000000]
        [--show "formation break"]

The first joint move of an episode that starts no shortest path is blamed on
- "follower" when the leader's move starts one with some other follower move (the follower did
  not answer the move the leader made);
- "leader" when no follower move would have made the leader's move start one;
- "no path" when no successful path was left at all (the team's earlier moves cannot be the
  cause: this counts states the planner finds hopeless from the start).
Prints, per outcome, how many episodes had their first departure blamed on whom; whether a
successful path was still left after that departure ("yes", a longer one), none was ("no") or the
move itself ended the episode ("ends there"); and whether the leader's move there was the default
teacher's label ("label", on a first step the robust one) or another move ("other"). Then how far, at
the follower's first departures, its Q-value for the move it made stood above its best move that starts
a shortest path with the leader's (one follower). ``--show OUTCOME`` also lists each episode that ended
so: the step of its first departure, the joint move made there and the teacher's label, and the step it
ended at.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.learn.config import TrainSettings
from formation.learn.qnet import team_q_values
from formation.learn.teacher import Teacher
from formation.planner import shortest_first_moves, shortest_path
from formation.policy import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="an exported policy folder or a run folder")
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--seed", type=int, default=2_000_000)
    parser.add_argument("--show", help="an outcome whose episodes to list, e.g. 'formation break'")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load(args.policy)
    config = policy.game
    defaults = TrainSettings()
    teacher = Teacher(config, defaults.planner_slack, defaults.label_order, defaults.robust_first_step)
    first: dict[int, tuple[str, str, str]] = {}  # episode -> (who, a path left after?, leader's move)
    where: dict[int, tuple[int, tuple, tuple | None]] = {}  # episode -> (step, joint move, label) of that move
    moves = collections.Counter()
    follower_gaps: list[float] = []  # at the follower's first departures: Q of the move made - best Q on a path
    q_now: dict[str, np.ndarray] = {}

    def act(obs: np.ndarray) -> np.ndarray:
        # as `formation evaluate` plays: within the safety heads' moves, if any
        moves, by_module = policy.act_batch_and_q(obs)
        # (N, agents, 4): each agent's Q-values, the follower's in the row of the move the leader makes
        q_now["q"] = team_q_values(by_module, policy.agent_modules, leader_moves=moves[:, 0])
        return moves

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        for i in np.flatnonzero(live):
            if i in first:
                continue
            scenario = game.scenario(i)
            found = shortest_first_moves(scenario, config=config)
            if found is None:
                first[i] = ("no path", "no", "")
                continue
            starts = set(found[1])
            joint = tuple(int(a) for a in actions[i])
            moves["on a shortest path"] += joint in starts
            moves["all"] += 1
            if joint in starts:
                continue
            who = "follower" if any(s[0] == joint[0] for s in starts) else "leader"
            if who == "follower" and len(joint) == 2:
                q = q_now["q"][i, 1]
                follower_gaps.append(float(q[joint[1]] - max(q[s[1]] for s in starts if s[0] == joint[0])))
            after = game.scenario(i)  # the state the joint move leads to, played on a copy
            probe = type(game)(config, batch_size=1)
            probe.reset()
            probe.load([after.to_dict()])
            probe.step(np.asarray([joint]))
            alive = not (probe.done[0] and not probe.success[0])
            left = ("ends there" if not alive else "yes" if probe.success[0] or
                    shortest_path(probe.scenario(0), config=config) is not None else "no")
            label = teacher.label(scenario, first_step=game.steps[i] == 0)
            first[i] = (who, left, "label" if label is not None and label[0] == joint[0] else "other")
            where[i] = (int(game.steps[i]), joint, label)

    played = play_greedy(config, act, args.episodes, args.seed, watch=watch)
    outcome = {i: ("success" if played["success"][i] else "leader collision" if played["leader_collided"][i]
                   else "follower collision" if played["follower_collided"][i]
                   else "formation break" if played["broken"][i] else "time-out") for i in range(args.episodes)}
    print(f"{args.policy}: {args.episodes} episodes (seed {args.seed}); joint moves that start a shortest "
          f"path: {moves['on a shortest path'] / max(moves['all'], 1):.2%} of {moves['all']}")
    table = collections.Counter()
    for i, end in outcome.items():
        table[(end, *first.get(i, ("never", "yes", "")))] += 1
    print(f"{'outcome':<20} {'first off':<10} {'path left after':<16} {'leader moved':<13} {'episodes':>8}")
    for (end, who, left, leader), n in sorted(table.items()):
        print(f"{end:<20} {who:<10} {left:<16} {leader:<13} {n:>8}")
    if follower_gaps:
        low, mid, high = np.quantile(follower_gaps, [0.25, 0.5, 0.75])
        print(f"at the follower's {len(follower_gaps)} first departures, its Q-value for the move made stood "
              f"{mid:.1f} (quartiles {low:.1f}, {high:.1f}) above its best move on a shortest path")
    for i, end in outcome.items():
        if end == args.show:
            step, joint, label = where.get(i, (None, None, None))
            print(f"episode {i}: first off at step {step}, joint move {joint}, label {label}; "
                  f"ended at step {played['steps'][i]}")


if __name__ == "__main__":
    main()
