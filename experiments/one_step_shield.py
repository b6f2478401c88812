"""How many of a policy's failures a one-step safety layer could save: play the policy greedily and,
whenever the team's joint move would end the episode in a failure (a collision or a formation break) on
this very step, play instead a joint move that does not, chosen with the game's true state (so this is
an upper bound for any shield that looks one step ahead; it is a diagnostic, not part of any policy).

    .venv/bin/python experiments/one_step_shield.py policies/setting2 [--who team|follower]
        [--episodes 1000] [--seed 2000000]

``--who follower`` keeps the leader's move and only replaces the followers' (the first surviving joint
move in the order of ``itertools.product``); ``team`` (the default) falls back to any joint move when no
follower move saves the leader's. Prints the summary of the shielded play and how often a move was
replaced (by whom) or could not be (every joint move fails: the team was already trapped).
"""

from __future__ import annotations

import argparse
import collections
import itertools
from pathlib import Path

import numpy as np
import torch

from formation.evaluate import play_greedy
from formation.game import BatchedGame
from formation.policy import load


def failing(config, scenarios: list[dict], joints: np.ndarray) -> np.ndarray:
    """Whether each ``joints[k]`` played from ``scenarios[k]`` ends the episode in a failure this step."""
    game = BatchedGame(config, batch_size=len(scenarios))
    game.reset()
    game.load(scenarios)
    game.step(joints)
    return game.done & ~game.success & ~game.truncated


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("policy", type=Path, help="an exported policy folder or a run folder")
    parser.add_argument("--who", choices=("team", "follower"), default="team")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2_000_000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = load(args.policy)
    config = policy.game
    joints = np.asarray(list(itertools.product(range(4), repeat=1 + config.n_followers)))
    replaced = collections.Counter()

    def shield(game, actions: np.ndarray, live: np.ndarray) -> None:
        live_games = np.flatnonzero(live)
        bad = failing(config, [game.scenario(i).to_dict() for i in live_games], actions[live_games])
        for i in live_games[bad]:
            state = game.scenario(i).to_dict()
            candidates = joints[joints[:, 0] == actions[i, 0]]  # the leader's own move first
            saved = candidates[~failing(config, [state] * len(candidates), candidates)]
            who = "followers"
            if not len(saved) and args.who == "team":
                saved, who = joints[~failing(config, [state] * len(joints), joints)], "leader"
            if len(saved):
                actions[i] = saved[0]
                replaced[who] += 1
            else:
                replaced["none saves"] += 1

    played = play_greedy(config, policy.act_batch, args.episodes, args.seed, watch=shield)
    summary = {k: v for k, v in played["summary"].items() if k != "return_mean"}
    print(f"{args.policy} with a one-step shield ({args.who}): {summary}")
    print(f"moves replaced: {dict(replaced)}")


if __name__ == "__main__":
    main()
