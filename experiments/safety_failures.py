"""Where a team with safety heads fails: its first joint move that the planner finds unsafe over the heads'
horizon, in every failed episode of vetoed greedy play (as ``formation evaluate`` plays it).

    .venv/bin/python experiments/safety_failures.py policies/setting2 [--episodes 1000] [--seed 3000000]

Each failure is put in one of these, at that first unsafe move:
- ``no safe move left``: the planner finds no joint move safe over the horizon either (the move before it was
  safe over the horizon but led to a dead end beyond it: a longer horizon would be needed);
- ``judged safe``: a safe move was left, and the heads judged the team's unsafe move safe;
- ``none judged safe``: a safe move was left, but the heads judged no move safe, and the Q-values chose;
and, among each, how many came on an episode's first step (whose screens do not show the obstacles' motion).
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.learn.teacher import safety_labels
from formation.policy import load

BIT = np.uint64(1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="a run folder or an exported policy folder")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3_000_000)
    parser.add_argument("--horizon", type=int, default=4)
    args = parser.parse_args()
    torch.set_num_threads(2)
    policy = load(args.policy)
    if not policy.learned_veto:
        raise SystemExit(f"{args.policy}: its networks have no safety head (train.safety_horizon: 0)")
    config = policy.game
    first_unsafe: dict[int, tuple[str, int]] = {}  # episode -> (kind, step)
    seen: dict[str, np.ndarray] = {}

    def act(obs: np.ndarray) -> np.ndarray:
        seen["obs"] = obs
        return policy.act_batch(obs)

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        idx = np.array([i for i in np.flatnonzero(live) if int(i) not in first_unsafe], np.int64)
        if not len(idx):
            return
        truth = safety_labels([game.scenario(int(i)) for i in idx], game.steps[idx], config, args.horizon, 0, 0)
        truth = ((truth[:, None] >> np.arange(16, dtype=np.uint64)) & BIT).astype(bool)
        judged = policy.learned_safe_moves(seen["obs"][idx]).reshape(-1, 16)
        own = 4 * actions[idx, 0] + actions[idx, 1]
        for k, i in enumerate(idx.tolist()):
            if truth[k, own[k]]:
                continue
            if not truth[k].any():
                kind = "no safe move left"
            elif judged[k, own[k]]:
                kind = "judged safe"
            else:
                kind = "none judged safe"
            first_unsafe[i] = (kind, int(game.steps[i]))

    played = play_greedy(config, act, args.episodes, args.seed, watch=watch)
    failed = np.flatnonzero(~played["success"])
    kinds = Counter(first_unsafe[i][0] if i in first_unsafe else "never unsafe" for i in failed.tolist())
    first = Counter(first_unsafe[i][0] for i in failed.tolist() if i in first_unsafe and first_unsafe[i][1] == 0)
    s = played["summary"]
    print(f"{args.policy}: success {s['success']:.1%} of {args.episodes} (seed {args.seed}); "
          f"{len(failed)} failures by their first move unsafe over {args.horizon} steps:")
    for kind, count in kinds.most_common():
        print(f"  {kind}: {count} ({first.get(kind, 0)} on the first step)")
    print("  steps of that move: " + ", ".join(str(first_unsafe[i][1]) for i in failed.tolist() if i in first_unsafe))


if __name__ == "__main__":
    main()
