"""Where a refitted team fails, seen from its veto's fallback: in each failed episode of vetoed greedy play (as
``formation evaluate`` plays it), its first joint move that no continuation survives over ``--horizon`` steps.

    .venv/bin/python experiments/veto_fallback.py policies/setting3 [--seed 3000000] [--margins 0.05 0.1 0.2]

For each failure it prints whether any joint move was above the veto's threshold there, whether the move the
heads judge the most probably safe was safe (by the planner), and, for a collision, where the obstacle nearest
the agent that collided at the end stood at that move (row and column from the leader; inside the networks'
leader window or not). With ``--margins``, it also plays the team with a looser fallback: where no move is
above the threshold, the moves within each margin of the most probable one, the Q-values choosing among them.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import torch

import formation.policy as policy_module
from formation.evaluate import play_greedy
from formation.learn.teacher import safety_labels
from formation.policy import load

BIT = np.uint64(1)


def within_margin(margin: float):
    """A ``within_veto`` whose fallback keeps the moves within ``margin`` of the most probable one."""
    def rule(p: np.ndarray, threshold: float, fallback: str = "") -> np.ndarray:
        strict = p > threshold
        near = p >= p.max(axis=(1, 2), keepdims=True) - margin
        return np.where(strict.any(axis=(1, 2), keepdims=True), strict, near)
    return rule


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="a run folder or an exported policy folder with safety heads")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=3_000_000)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--margins", type=float, nargs="*", default=[])
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load(args.policy)
    if not policy.learned_veto:
        raise SystemExit(f"{args.policy}: its networks have no safety head (train.safety_horizon: 0)")
    config, window = policy.game, policy.specs[policy.agent_modules[0]].window
    first: dict[int, dict] = {}  # episode -> what the first unsafe move met
    history: dict[int, list] = {}  # episode -> (positions, obstacle rows, obstacle columns) of every step
    seen: dict = {}

    def act(obs: np.ndarray) -> np.ndarray:
        seen["obs"] = obs
        return policy.act_batch(obs)

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        for i in np.flatnonzero(live).tolist():
            history.setdefault(i, []).append((game.positions[i].copy(), game.obstacle_rows[i].copy(),
                                           game.obstacle_cols[i].copy()))
        idx = np.array([i for i in np.flatnonzero(live) if int(i) not in first], np.int64)
        if not len(idx):
            return
        truth = safety_labels([game.scenario(int(i)) for i in idx], game.steps[idx], config, args.horizon, 0, 0)
        truth = ((truth[:, None] >> np.arange(16, dtype=np.uint64)) & BIT).astype(bool)
        p = policy.outputs(seen["obs"][idx])[1].reshape(len(idx), 16)
        own = 4 * actions[idx, 0] + actions[idx, 1]
        for k, i in enumerate(idx.tolist()):
            if not truth[k, own[k]]:
                first[i] = {"step": len(history[i]) - 1, "above": bool((p[k] > policy.veto_threshold).any()),
                            "likeliest_safe": bool(truth[k, p[k].argmax()]), "safe_left": bool(truth[k].any())}

    played = play_greedy(config, act, args.episodes, args.seed, watch=watch)
    failed = np.flatnonzero(~played["success"]).tolist()
    print(f"{args.policy}: success {played['summary']['success']:.1%} of {args.episodes} (seed {args.seed}), "
          f"veto above {policy.veto_threshold:g} (else {policy.veto_fallback}); {len(failed)} failures:")
    counts: Counter = Counter()
    for i in failed:
        if i not in first:
            print(f"  episode {i}: no move unsafe over {args.horizon} steps")
            continue
        f = first[i]
        who = 0 if played["leader_collided"][i] else 1 if played["follower_collided"][i] else None
        where = ""
        if who is not None:
            end_pos, end_rows, end_cols = history[i][-1]
            o = int((np.abs(end_rows - end_pos[who, 0]) + np.abs(end_cols - end_pos[who, 1])).argmin())
            pos, rows, cols = history[i][f["step"]]
            dr, dc = int(rows[o] - pos[0, 0]), int(cols[o] - pos[0, 1])
            inside = window is None or (-window[0] <= dr <= window[1] and abs(dc) <= window[2])
            where = (f"; the obstacle that hit at row {dr:+d}, column {dc:+d} from the leader "
                     f"({'inside' if inside else 'outside'} the window), {len(history[i]) - 1 - f['step']} steps "
                     f"before the end")
            counts["collisions, obstacle inside the window"] += inside
        kind = "leader collision" if who == 0 else "follower collision" if who == 1 else "other"
        print(f"  episode {i} ({kind}), step {f['step']}: a move above the threshold: {f['above']}, "
              f"the most probably safe move safe: {f['likeliest_safe']}, a safe move left: {f['safe_left']}{where}")
        counts["none above the threshold"] += not f["above"]
        counts["none above, the most probable safe"] += not f["above"] and f["likeliest_safe"]
        counts["collisions"] += who is not None
    print("  " + ", ".join(f"{k}: {v}" for k, v in counts.items()))
    original = policy_module.within_veto
    try:
        for margin in args.margins:
            policy_module.within_veto = within_margin(margin)
            s = play_greedy(config, policy.act_batch, args.episodes, args.seed)["summary"]
            print(f"{args.policy}: within {margin:g} of the most probable where none is above the threshold: "
                  f"success {s['success']:.1%}")
    finally:
        policy_module.within_veto = original


if __name__ == "__main__":
    main()
