"""Speed of the clairvoyant planner (``formation.planner.shortest_path``) on random scenarios.

Run: ``.venv/bin/python benchmarks/planner_speed.py [n_scenarios]`` (default 50 per setting).
Prints, per named setting, the mean and max milliseconds per scenario, the fraction solved, and
the fraction solved in exactly the lower bound of steps (scenarios from ``BatchedGame.reset(seed)``,
seeds 0..n-1, as ``env.reset(seed=i)`` draws them).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame
from formation.planner import lower_bound, shortest_path


def main(n_scenarios: int = 50) -> None:
    print(f"{'setting':>7} {'mean ms':>8} {'max ms':>8} {'solved':>9} {'in lower bound':>15}")
    for setting in (1, 2, 3, 4):
        config = GameConfig.from_setting(setting)
        game = BatchedGame(config, batch_size=1)
        times, solved, at_bound = [], 0, 0
        for seed in range(n_scenarios):
            game.reset(seed=seed)
            scenario = game.scenario(0)
            start = time.perf_counter()
            path = shortest_path(scenario, config=config)
            times.append(time.perf_counter() - start)
            if path is not None:
                solved += 1
                at_bound += len(path) == lower_bound(scenario, config)
        ms = np.array(times) * 1e3
        print(f"{setting:>7} {ms.mean():>8.1f} {ms.max():>8.1f} {f'{solved}/{n_scenarios}':>9} "
              f"{f'{at_bound}/{n_scenarios}':>15}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 50)
