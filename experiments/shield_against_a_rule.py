"""What the safety shield (``formation.shield``) does on its own: a trained team behind it, against a
hand-written rule behind the same shield. The rule knows nothing of obstacles: the leader heads for the
destination (forward-right or forward-left until it is in the destination's column, then forward) and
the follower copies the leader's move; the shield then vetoes its moves as it vetoes the networks'.

    .venv/bin/python experiments/shield_against_a_rule.py policies/setting2 [--horizons 0 1 2 4]
        [--episodes 1000] [--seed 2000000]

Prints, per horizon (0: no shield), the success rate, failures and mean steps of successes of both.
"""

from __future__ import annotations

import numpy as np
from _common import one_thread, policy_parser

from formation.evaluate import play_greedy
from formation.policy import load
from formation.recipe.qnet import N_ACTIONS
from formation.shield import FrameReader, Shield, shielded_moves


def heading_rule_preferences(obs: np.ndarray, reader: FrameReader, destination_col: int
                             ) -> tuple[np.ndarray, np.ndarray]:
    """The rule as Q-like preferences: the leader's (N, 4), highest for the move towards the destination's
    column (forward once there), then forward; the follower's answers (N, 4, 4), highest for the leader's move."""
    n = len(obs)
    leader = np.tile([0.5, 0.2, 0.2, 0.0], (n, 1))
    for i in range(n):
        where = np.argwhere(reader.kinds(obs[i], 0)["leader"])
        col = int(where[0, 1]) if len(where) else destination_col
        leader[i, 0 if col == destination_col else 2 if col < destination_col else 1] = 1.0
    follower = np.tile(np.eye(N_ACTIONS) + [0.1, 0.1, 0.1, 0.0], (n, 1, 1))
    return leader, follower


def main() -> None:
    parser = policy_parser(__doc__)
    parser.add_argument("--horizons", type=int, nargs="+", default=[0, 1, 2, 4], help="shield steps (0: none)")
    args = parser.parse_args()
    one_thread()
    policy = load(args.policy)
    config = policy.game
    reader = FrameReader(config)
    destination_col = config.destination[1]
    for horizon in args.horizons:
        shield = Shield(config, horizon) if horizon else None

        def rule(obs: np.ndarray, shield: Shield | None = shield) -> np.ndarray:
            leader, follower = heading_rule_preferences(obs, reader, destination_col)
            allowed = shield.allowed(obs) if shield is not None else np.ones((len(obs), 4, 4), bool)
            return shielded_moves(leader, follower, allowed)

        for name, act in (("networks", policy.shielded(horizon).act_batch), ("heading rule", rule)):
            s = play_greedy(config, act, args.episodes, args.seed)["summary"]
            steps = f"{s['steps_success_mean']:.2f}" if s["steps_success_mean"] is not None else "-"
            print(f"setting {config.setting} horizon {horizon} {name:12s} success {s['success']:.1%} "
                  f"(95% CI {s['success_ci95'][0]:.1%}-{s['success_ci95'][1]:.1%})  leader collision "
                  f"{s['leader_collision']:.1%}  follower collision {s['follower_collision']:.1%}  "
                  f"break {s['formation_broken']:.1%}  time-out {s['timeout']:.1%}  steps {steps}", flush=True)


if __name__ == "__main__":
    main()
