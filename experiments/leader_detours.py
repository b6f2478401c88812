"""Where a team's successes lose steps against the planner (docs/RESULTS.md, "One command per setting"):
the leader's waits, its moves along row 0 (sliding sideways to the destination), and its column offset from
the destination as it first reaches some rows, over the successes of the first N validation scenarios; and where
the time-outs end: how far the leader stands below the destination and beside it (docs/RESULTS.md, "One team for
every setting and team size").

    .venv/bin/python experiments/leader_detours.py POLICY [N] [SETTING FOLLOWERS]
    # POLICY: a run, its checkpoint/, an export; SETTING FOLLOWERS: the game of a team of many games
"""

import sys

import numpy as np

from formation.evaluate import play_greedy
from formation.policy import load

STAY = 3  # the action S (docs/GAME.md, 'Actions')
VALIDATION_SEED = 3_000_000


def main(path: str, n: int = 200, setting: int | None = None, followers: int | None = None) -> None:
    policy = load(path)
    if setting is not None:
        policy = policy.for_game(setting=setting, n_followers=followers)
    seen = []  # (leader's position before the step, its action, live) of every step

    def watch(game, actions, live):
        seen.append((game.positions[:, 0].copy(), actions[:, 0].copy(), live.copy()))

    played = play_greedy(policy.game, policy.act_batch, n, VALIDATION_SEED, watch=watch)
    won = np.asarray(played["success"])
    waits, on_top = np.zeros(n), np.zeros(n)
    for at, action, live in seen:
        waits += live & (action == STAY)
        on_top += live & (action != STAY) & (at[:, 0] == 0)
    print(f"{won.sum()}/{n} successes in {np.asarray(played['steps'])[won].mean():.2f} steps; per success, the "
          f"leader waits {waits[won].mean():.2f} times and moves along row 0 {on_top[won].mean():.2f} times")
    column = policy.game.destination[1]
    for row in (policy.game.height - 10, policy.game.height // 2, 12, 1):
        offset = np.full(n, np.nan)
        for at, _, live in seen:
            first = live & (at[:, 0] == row) & np.isnan(offset)
            offset[first] = at[first, 1] - column
        print(f"row {row}: the leader's mean column offset from the destination {np.nanmean(offset[won]):+.2f}")
    timeouts = np.asarray(played["timeout"])
    if timeouts.any():
        last = np.zeros((n, 2), np.int64)  # the leader's cell before each game's last step
        for at, _, live in seen:
            last[live] = at[live]
        below = last[timeouts, 0] - policy.game.destination[0]
        beside = np.abs(last[timeouts, 1] - column)
        side = (policy.specs["leader"].window or (0, 0, policy.game.width))[2]  # columns the leader sees either side
        print(f"{timeouts.sum()} time-outs: the leader ends {np.median(below):.0f} rows below the destination and "
              f"{np.median(beside):.0f} columns beside it (medians); {(beside > below).mean():.0%} more columns "
              f"beside it than rows below it, {(beside > side).mean():.0%} beyond the window's {side} columns")


if __name__ == "__main__":
    main(sys.argv[1], *(int(a) for a in sys.argv[2:5]))
