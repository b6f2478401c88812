"""Greedy play with the Q-values of the first policy, vetoed by the safety heads of several: do heads
trained in different runs make the same mistakes?

    .venv/bin/python experiments/safety_ensemble.py policies/setting2 /tmp/p_other [--rule all]
        [--threshold 0.97] [--episodes 1000] [--seed 3000000]

Each policy's heads give every joint move a probability of being safe (the mean of its networks'
heads, as ``formation evaluate`` uses them). ``--rule mean``: the mean over the policies; ``--rule all``:
the least of them (a move is above the threshold where every policy judges it so). The team keeps to the
moves above ``--threshold`` (default: the first policy's ``veto_threshold``) as ``formation evaluate``
does (``formation.policy.within_veto``: where none is above it, those the first policy's ``veto_fallback``
names). Prints the success rate with the first policy's heads alone and with all of them. Two refits of one
team (``formation refit``) share its Q-values and differ in their heads alone.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.policy import PolicyError, greedy_within, load, within_veto


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", type=Path, nargs="+",
                        help="run folders or exported policy folders; the first plays")
    parser.add_argument("--rule", choices=("mean", "all"), default="all")
    parser.add_argument("--threshold", type=float, help="the veto's threshold (default: the first policy's)")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        policies = [load(p) for p in args.policies]
    except PolicyError as err:
        raise SystemExit(f"safety_ensemble: {err}") from None
    for path, policy in zip(args.policies, policies):
        if not policy.learned_veto:
            raise SystemExit(f"{path}: its networks have no safety head (train.safety_horizon: 0)")
        if policy.game != policies[0].game:
            raise SystemExit(f"{path}: trained on another game than {args.policies[0]}")
    first = policies[0]
    threshold = first.veto_threshold if args.threshold is None else args.threshold
    if not 0.0 <= threshold < 1.0:
        raise SystemExit(f"--threshold: {threshold:g} not in [0, 1)")

    def act(obs: np.ndarray) -> np.ndarray:
        by_module, safe = first.outputs(obs)
        verdicts = [safe] + [p.outputs(obs)[1] for p in policies[1:]]
        combined = np.mean(verdicts, axis=0) if args.rule == "mean" else np.min(verdicts, axis=0)
        kept = within_veto(combined, threshold, first.veto_fallback)
        return greedy_within(by_module, first.agent_modules, None, kept)

    alone = play_greedy(first.game, first.with_veto_threshold(threshold).act_batch, args.episodes,
                        args.seed)["summary"]
    together = play_greedy(first.game, act, args.episodes, args.seed)["summary"]
    for name, summary in (("its own heads", alone),
                          (f"{len(policies)} policies' heads, rule {args.rule}", together)):
        print(f"{args.policies[0]} seed {args.seed}, threshold {threshold:g}, {name}: "
              f"success {summary['success']:.3f}, collisions "
              f"{summary['leader_collision']:.3f} / {summary['follower_collision']:.3f}, "
              f"breaks {summary['formation_broken']:.3f}")


if __name__ == "__main__":
    main()
