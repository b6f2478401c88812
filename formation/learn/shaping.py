"""Potential-based reward shaping (Ng, Harada and Russell 1999), a training option.

The stored reward of a step becomes ``r + w * (gamma * Phi(s') - Phi(s))``; the game's own reward
(the paper's) is untouched, and so are the optimal policies. Potentials, per agent:

- ``distance``: the leader's minus Chebyshev distance to the destination (its steps to go,
  ignoring obstacles); 0 for followers.
- ``planner``: minus the clairvoyant planner's shortest remaining path for everyone, searched up
  to the lower bound + ``slack`` steps; a longer or missing path, or a lost game, counts as
  ``H + W`` steps.
"""

from __future__ import annotations

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame

POTENTIALS = ("none", "distance", "planner")


class Potential:
    def __init__(self, kind: str, config: GameConfig, slack: int = 6):
        if kind not in POTENTIALS:
            raise ValueError(f"train.potential: {kind!r} is not allowed; allowed: {', '.join(POTENTIALS)}")
        self.kind, self.config, self.slack = kind, config, slack
        self._destination = np.array(config.destination)
        self._lost = float(config.height + config.width)
        self._capped: dict[int, GameConfig] = {}

    def __call__(self, game: BatchedGame, mask: np.ndarray | None = None) -> np.ndarray:
        """Phi of every agent of the games where ``mask`` is True (others 0), shape (B, 1+k)."""
        phi = np.zeros((game.batch_size, game.n_agents), np.float32)
        if self.kind == "distance":
            phi[:, 0] = -np.abs(game.positions[:, 0] - self._destination).max(axis=1)
        elif self.kind == "planner":
            from formation.planner import lower_bound, shortest_path

            games = range(game.batch_size) if mask is None else np.flatnonzero(mask).tolist()
            for i in games:
                if game.success[i]:
                    continue
                if game.terminated[i]:
                    phi[i] = -self._lost
                    continue
                scenario = game.scenario(i)
                limit = lower_bound(scenario, self.config) + self.slack
                if limit not in self._capped:
                    self._capped[limit] = self.config.replace(max_steps=limit)
                path = shortest_path(scenario, config=self._capped[limit])
                phi[i] = -(len(path) if path is not None else self._lost)
        if mask is not None:
            phi[~mask] = 0
        return phi
