"""How strict the safety heads' veto should be: the team of a run or export with safety heads
(``train.safety_horizon``) played greedily within the joint moves whose mean safe probability is above each
threshold (``formation evaluate`` uses the policy's ``veto_threshold``: one half, or what ``formation refit``
set), on the same scenarios (``Policy.with_veto_threshold``).

    .venv/bin/python experiments/veto_threshold.py policies/setting4 [--thresholds 0.5 0.7 0.9] [--seed 3000000]

Where no joint move is above a threshold, the team keeps to those the policy's ``veto_fallback`` names
(as ``formation evaluate``; ``--veto-fallback`` of ``formation evaluate`` to try the other). Prints one
summary per threshold.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from formation.evaluate import play_greedy
from formation.policy import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="a run folder or an exported policy folder")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.5, 0.7, 0.9])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3_000_000)
    args = parser.parse_args()
    bad = [t for t in args.thresholds if not 0.0 <= t < 1.0]
    if bad:
        raise SystemExit(f"--thresholds: {bad} not in [0, 1)")
    torch.set_num_threads(1)
    policy = load(args.policy)
    if not policy.learned_veto:
        raise SystemExit(f"{args.policy}: its networks have no safety head (train.safety_horizon: 0)")
    for threshold in args.thresholds:
        act = policy.with_veto_threshold(threshold).act_batch
        summary = play_greedy(policy.game, act, args.episodes, args.seed)["summary"]
        s = {k: v for k, v in summary.items() if k not in ("return_mean",)}
        print(f"{args.policy} threshold {threshold}: {s}", flush=True)


if __name__ == "__main__":
    main()
