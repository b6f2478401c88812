"""Where a team with safety heads (``train.safety_horizon``) fails: in the episodes where the heads' veto
changed the team's joint move at least once, or in the others. The team plays greedily within the moves
its heads judge safe, as ``formation evaluate`` plays it, and each step is compared with the move the
Q-values alone would make.

    .venv/bin/python experiments/veto_episodes.py policies/setting2 [--episodes 1000] [--seed 3000000]

Prints the success rate, the number of episodes the veto acted in, and the failures among them and
among the others.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.policy import PolicyError, load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="a run folder or an exported policy folder")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        policy = load(args.policy)
    except PolicyError as err:
        raise SystemExit(f"veto_episodes: {err}") from None
    if not policy.learned_veto:
        raise SystemExit(f"{args.policy}: its networks have no safety head (train.safety_horizon: 0)")
    q_alone = policy.without_learned_veto()
    vetoed = np.zeros(args.episodes, bool)
    changed: list[np.ndarray] = []

    def act(obs: np.ndarray) -> np.ndarray:
        moves = policy.act_batch(obs)
        changed[:] = [(moves != q_alone.act_batch(obs)).any(axis=1)]
        return moves

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        vetoed[live & changed[0]] = True

    result = play_greedy(policy.game, act, args.episodes, args.seed, watch=watch)
    failed = ~np.asarray(result["success"], bool)
    print(f"{args.policy} seed {args.seed}: success {result['summary']['success']:.3f}; the veto changed a move in "
          f"{vetoed.sum()} of {args.episodes} episodes, {(failed & vetoed).sum()} of them failed; "
          f"{(failed & ~vetoed).sum()} failures in the other {(~vetoed).sum()}")


if __name__ == "__main__":
    main()
