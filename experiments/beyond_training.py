"""A trained team on scenarios its training never drew, so that users know where it stops working.

    .venv/bin/python experiments/beyond_training.py policies/setting3 [--episodes 1000] [--seed 2000000]
        [--workers 2]

The game's generator puts each obstacle in a row of the band [H//5, H - H//5) at speed 1 or 2; training
and the docs' test scenarios come from it. Here the same team plays, greedily as `formation evaluate`:
- as trained: the generator's scenarios (the reference row);
- any row: the obstacles in any row between the destination's and the agents' start rows (rows 1 to H-2,
  less the rows the agents start in), closer to the start and to the destination than the band allows;
- more obstacles: the generator's, with 2 and with 4 obstacles more than the setting's (still one a row);
- faster: speeds drawn from 1, 2 and 3 cells a step (the networks' forecast knows 1 and 2).
Prints a Markdown table: success with its 95% interval, how the other episodes ended, how many scenarios the
clairvoyant planner solves (some of these are lost for any team), and the steps of the team's successes
against the planner's on the same scenarios.
"""

from __future__ import annotations

import numpy as np
from _common import one_thread, policy_parser

from formation.config import GameConfig
from formation.evaluate import planner_reference, play_greedy
from formation.policy import load


def any_row_scenarios(config: GameConfig, episodes: int, seed: int) -> list[dict]:
    """The generator's scenarios with each obstacle moved to a row drawn (distinct) from rows 1 to H-2 less
    the agents' start rows; columns and velocities as drawn."""
    from formation.game import BatchedGame

    game = BatchedGame(config, batch_size=episodes, seed=seed)
    game.reset()
    leader, followers = config.starts
    taken = {leader[0], *(f[0] for f in followers)}
    rows = [r for r in range(1, config.height - 1) if r not in taken]
    rng = np.random.default_rng(seed)
    out = []
    for i in range(episodes):
        scenario = game.scenario(i).to_dict()
        new_rows = rng.choice(rows, size=len(scenario["obstacles"]), replace=False)
        scenario["obstacles"] = [[int(r), c, v] for r, (_, c, v) in zip(new_rows, scenario["obstacles"], strict=True)]
        out.append(scenario)
    return out


def variants(config: GameConfig, episodes: int, seed: int) -> list[tuple[str, GameConfig, list | None]]:
    o = config.n_obstacles
    return [("as trained", config, None),
            ("any row", config, any_row_scenarios(config, episodes, seed)),
            (f"{o + 2} obstacles", config.replace(n_obstacles=o + 2), None),
            (f"{o + 4} obstacles", config.replace(n_obstacles=o + 4), None),
            ("speeds 1-3", config.replace(obstacle_speeds=[1, 2, 3]), None)]


def main() -> None:
    parser = policy_parser(__doc__)
    parser.add_argument("--workers", type=int, default=2, help="planner processes (default 2)")
    args = parser.parse_args()
    one_thread()
    policy = load(args.policy)
    print(f"{args.policy}: setting {policy.game.setting}, {args.episodes} scenarios from seed {args.seed:,}\n")
    print("| scenarios | success (95% CI) | leader collision | follower collision | formation break | time-out "
          "| planner solves | steps: ours / planner |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, config, scenarios in variants(policy.game, args.episodes, args.seed):
        played = play_greedy(config, policy.act_batch, args.episodes, args.seed, scenarios=scenarios)
        reference = planner_reference(config, played["scenarios"], args.workers)
        s = played["summary"]
        both = np.asarray(played["success"]) & reference["solved"]
        steps = (f"{played['steps'][both].mean():.2f} / {reference['steps'][both].mean():.2f}" if both.any()
                 else "none")
        low, high = s["success_ci95"]
        print(f"| {name} | {s['success']:.1%} ({low:.1%}-{high:.1%}) | {s['leader_collision']:.1%} | "
              f"{s['follower_collision']:.1%} | {s['formation_broken']:.1%} | {s['timeout']:.1%} | "
              f"{reference['solved'].mean():.1%} | {steps} |", flush=True)


if __name__ == "__main__":
    main()
