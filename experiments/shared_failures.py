"""Whether trained teams fail the same scenarios: each team (run folders or exports of the same game) plays
the same episodes greedily, as ``formation evaluate`` plays it; prints each team's success, how many
episodes exactly k of the teams fail, and the success of the best of them per episode (an oracle that
picks, after the fact, a team that won). Failures most teams share are systematic, not the noise of one
training run, and neither more seeds nor an ensemble will remove them.

    .venv/bin/python experiments/shared_failures.py runs/s2_safety4 runs/s2_safety4_seed1 --episodes 1000 --seed 3000000
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.policy import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", nargs="+", help="run folders or `formation export` folders")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    teams = [load(path) for path in args.policies]
    game = teams[0].game
    if any(team.game != game for team in teams):
        parser.error("policies: all must be trained on the same game")
    failed = []
    for path, team in zip(args.policies, teams):
        played = play_greedy(game, team.act_batch, args.episodes, args.seed)
        failed.append(~played["success"])
        print(f"{path}: success {played['summary']['success']:.1%}", flush=True)
    by = np.sum(failed, axis=0)
    counts = ", ".join(f"{k}: {int((by == k).sum())}" for k in range(1, len(teams) + 1))
    print(f"episodes failed by exactly k of the {len(teams)} teams: {counts}")
    print(f"best of the {len(teams)} per episode: success {(by < len(teams)).mean():.1%}")


if __name__ == "__main__":
    main()
