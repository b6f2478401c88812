"""What a learnt safety head (``train.safety_horizon``) is worth: the team of a run or export played greedily
with the heads' veto (as ``formation evaluate`` plays it) and without, on the same scenarios; and how often
the heads' verdicts on the 16 joint moves agree with the planner's on the states of the vetoed play.

    .venv/bin/python experiments/safety_head.py runs/s2_safety4 [--horizon 4] [--episodes 1000] [--seed 2000000]

``--horizon``: the steps the verdicts are checked over, or ``path`` (with the run's ``train.safety_slack``
and ``planner_slack``); default: the run's ``train.safety_horizon``, or 4 for an export. Prints both
summaries, then the verdicts' errors: unsafe moves judged safe, safe moves judged unsafe, and the share
of states where the team's own move was unsafe.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.learn.config import SAFETY_PATH, RunConfig, TrainSettings
from formation.learn.teacher import safety_labels
from formation.policy import load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="a run folder or an exported policy folder")
    parser.add_argument("--horizon", type=lambda v: v if v == SAFETY_PATH else int(v))
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load(args.policy)
    if not policy.learned_veto:
        raise SystemExit(f"{args.policy}: its networks have no safety head (train.safety_horizon: 0)")
    saved = args.policy / "config.yaml"
    train = RunConfig.load_saved(saved).train if saved.is_file() else TrainSettings(safety_horizon=4)
    horizon = train.safety_horizon if args.horizon is None else args.horizon
    config = policy.game
    counts = {"unsafe judged safe": 0, "unsafe": 0, "safe judged unsafe": 0, "safe": 0, "own move unsafe": 0,
              "states": 0}
    bit = np.uint64(1)

    def check(game, actions: np.ndarray, live: np.ndarray) -> None:
        idx = np.flatnonzero(live)
        if not len(idx):
            return
        truth = safety_labels([game.scenario(int(i)) for i in idx], game.steps[idx], config, horizon,
                              train.safety_slack, train.planner_slack)
        truth = ((truth[:, None] >> np.arange(16, dtype=np.uint64)) & bit).astype(bool)
        judged = policy.learned_safe_moves(seen["obs"][idx]).reshape(-1, 16)
        counts["unsafe judged safe"] += int((judged & ~truth).sum())
        counts["unsafe"] += int((~truth).sum())
        counts["safe judged unsafe"] += int((~judged & truth).sum())
        counts["safe"] += int(truth.sum())
        own = 4 * actions[idx, 0] + actions[idx, 1]
        counts["own move unsafe"] += int((~truth[np.arange(len(idx)), own]).sum())
        counts["states"] += len(idx)

    seen: dict[str, np.ndarray] = {}

    def act(obs: np.ndarray) -> np.ndarray:  # the vetoed team, keeping what it saw for ``check``
        seen["obs"] = obs
        return policy.act_batch(obs)

    for name, team_act, watch in (("with the heads' veto", act, check),
                                  ("without it", policy.without_learned_veto().act_batch, None)):
        played = play_greedy(config, team_act, args.episodes, args.seed, watch=watch)
        s = {k: v for k, v in played["summary"].items() if k not in ("return_mean", "success_ci95")}
        print(f"{args.policy} {name}: {s}", flush=True)
    over = "on keeping a path" if horizon == SAFETY_PATH else f"over {horizon} steps"
    print(f"verdicts {over} on {counts['states']} states of the vetoed play: "
          f"unsafe judged safe {counts['unsafe judged safe']}/{counts['unsafe']}, "
          f"safe judged unsafe {counts['safe judged unsafe']}/{counts['safe']}, "
          f"the team's move unsafe in {counts['own move unsafe']}")


if __name__ == "__main__":
    main()
