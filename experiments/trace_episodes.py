"""Print a policy's greedy episodes move by move: how each ended, its steps, the team's joint moves
(leader's then follower's: F forward, L forward-left, R forward-right, S stay) and the leader's last cell.

    .venv/bin/python experiments/trace_episodes.py runs/s3_leader [--episodes 4] [--seed 2000000]

It shows habits the success rate hides, such as a leader that keeps sidestepping past the destination's
column ("RR RR RR ..." and then a time-out; docs/TRAINING.md, "Any move on a shortest path").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from formation.game import BatchedGame, Observer
from formation.policy import load

MOVE_LETTERS = "FLRS"  # the spec's actions 0..3


def trace(policy, seed: int) -> tuple[str, int, str, tuple[int, int]]:
    """(outcome, steps, joint moves, the leader's last cell) of one greedy episode from ``seed``."""
    game = BatchedGame(policy.game, batch_size=1)
    game.reset(seed=seed)
    observer = Observer(game)
    obs = observer.observe(np.ones(1, bool))
    moves = []
    while not game.done[0]:
        joint = policy.act_batch(obs)[0]
        moves.append("".join(MOVE_LETTERS[m] for m in joint))
        game.step(joint[None])
        obs = observer.observe(game.done.copy())
    if game.success[0]:
        outcome = "success"
    elif game.truncated[0]:
        outcome = "time-out"
    elif game.collided[0].any():
        outcome = "collision"
    else:
        outcome = "formation break"
    return outcome, int(game.steps[0]), " ".join(moves), game.scenario(0).leader


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="an exported policy folder or a run folder")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=2_000_000)
    args = parser.parse_args()
    policy = load(args.policy)
    for k in range(args.episodes):
        outcome, steps, moves, leader = trace(policy, args.seed + k)
        print(f"seed {args.seed + k}: {outcome} after {steps} steps, the leader at {leader}: {moves}")


if __name__ == "__main__":
    main()
