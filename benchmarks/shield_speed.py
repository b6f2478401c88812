"""The safety shield's cost: seconds to play greedy episodes with a trained team alone and behind shields
of several horizons (``formation.shield``), and the decisions per second.

    .venv/bin/python benchmarks/shield_speed.py [policies/setting2] [--horizons 0 2 4 6 8] [--episodes 1000]

One process, one torch thread; the episodes of seed 2000000 (docs/RESULTS.md), played at once.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.policy import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", nargs="?", default="policies/setting2")
    parser.add_argument("--horizons", type=int, nargs="+", default=[0, 2, 4, 6, 8])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load(args.policy)
    for horizon in args.horizons:
        team = policy.shielded(horizon)
        start = time.perf_counter()
        played = play_greedy(team.game, team.act_batch, args.episodes, args.seed)
        seconds = time.perf_counter() - start
        decisions = int(np.asarray(played["steps"]).sum())
        print(f"{args.policy} shield {horizon}: {args.episodes} episodes in {seconds:.1f} s, "
              f"{decisions / seconds:,.0f} team decisions/s, success {played['summary']['success']:.1%}", flush=True)


if __name__ == "__main__":
    main()
