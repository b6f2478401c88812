"""Greedy success of several trained teams acting together: each agent takes the action with the
highest Q-value averaged over the teams' networks (run folders or exports of the same game). A
follower that answers the leader reads, in every team's averaged network, the row of the move the
averaged leader makes. Teams with safety heads (``train.safety_horizon``) keep, as one team does, to
the joint moves whose safety probability, averaged over all their heads, is above one half
(``--no-veto``: whatever the heads say). ``--combine strict``: only to the joint moves that every team's
heads judge safe; ``vote``: each team picks its own joint move (behind its own heads) and the most
picked one is played (ties: the one ``mean`` would play, if tied, else the first).

    .venv/bin/python experiments/ensemble.py runs/s1_cells runs/s1_pix_win --episodes 1000 --seed 2000000

Shows how much of a team's failures are noise that another network would not share.
"""

from __future__ import annotations

import argparse

import numpy as np

from formation.evaluate import play_greedy
from formation.learn.qnet import team_q_values
from formation.policy import greedy_within, load


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policies", nargs="+", help="run folders or `formation export` folders")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2_000_000)
    parser.add_argument("--no-veto", action="store_true", help="ignore the teams' safety heads")
    parser.add_argument("--combine", choices=("mean", "strict", "vote"), default="mean")
    args = parser.parse_args()
    teams = [load(path) for path in args.policies]
    game = teams[0].game
    if any(team.game != game for team in teams):
        parser.error("policies: all must be trained on the same game")

    modules = teams[0].agent_modules
    if any(team.agent_modules != modules for team in teams):
        parser.error("policies: all must map the agents to the same modules")

    veto = not args.no_veto and any(team.learned_veto for team in teams)
    if veto and len(modules) != 2:
        parser.error("policies: the safety heads' veto needs one follower")
    if args.combine == "strict" and not veto:
        parser.error("--combine strict: needs teams with safety heads, and no --no-veto")

    def mean_act(obs: np.ndarray) -> np.ndarray:
        if not veto:
            q = {m: np.mean([team.q_values(obs, m) for team in teams], axis=0) for m in sorted(set(modules))}
            return team_q_values(q, modules).argmax(axis=-1)
        outputs = [team.outputs(obs) for team in teams]
        q = {m: np.mean([by_module[m] for by_module, _ in outputs], axis=0) for m in sorted(set(modules))}
        probabilities = [p for _, p in outputs if p is not None]
        safe = np.min(probabilities, axis=0) if args.combine == "strict" else np.mean(probabilities, axis=0)
        return greedy_within(q, modules, None, safe > 0.5)

    def vote_act(obs: np.ndarray) -> np.ndarray:
        picks = np.stack([(team if veto else team.without_learned_veto()).act_batch(obs) for team in teams])
        codes = picks[..., 0] * 4 + picks[..., 1]  # (teams, N) joint move indices
        votes = np.stack([(codes == j).sum(0) for j in range(16)], axis=1)  # (N, 16)
        fallback = mean_act(obs)
        fallback_code = fallback[:, 0] * 4 + fallback[:, 1]
        tied = votes == votes.max(axis=1, keepdims=True)
        best = np.where(tied[np.arange(len(obs)), fallback_code], fallback_code, tied.argmax(axis=1))
        return np.stack([best // 4, best % 4], axis=1)

    if args.combine == "vote" and len(modules) != 2:
        parser.error("--combine vote: one follower only")
    act = vote_act if args.combine == "vote" else mean_act

    summary = play_greedy(game, act, args.episodes, args.seed)["summary"]
    print(f"{' + '.join(args.policies)}: {args.episodes} episodes (seed {args.seed}), "
          f"{'with' if veto else 'without'} the heads' veto, combined by {args.combine}")
    for key in ("success", "leader_collision", "follower_collision", "formation_broken", "timeout"):
        print(f"{key:<20} {summary[key]:.1%}")


if __name__ == "__main__":
    main()
