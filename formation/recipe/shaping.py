"""Potential-based reward shaping (Ng, Harada and Russell 1999), a training option.

The stored reward of a step becomes ``r + w * (gamma * Phi(s') - Phi(s))``; the game's own reward
(the paper's) is untouched. Over an episode the shaping sums to ``w * (gamma^T Phi(s_T) - Phi(s_0))``. Where
the leader reaches, ``Phi(s_T)`` is 0; where a collision or break ends the episode, ``s_T`` is where it ended
and nothing bootstraps after it, so that end is charged ``w`` times the steps the leader had left (discounted),
on top of the game's -1s. That charge is not policy-invariant (Ng et al. take ``Phi`` of an ending as 0):
it makes ending far from the destination dearer than ending near it. The potential, per agent: the leader's
minus Chebyshev distance to the destination (its steps to go, ignoring obstacles); 0 for followers.
"""

from __future__ import annotations

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame


class Potential:
    def __init__(self, config: GameConfig):
        self.config = config
        self._destination = np.array(config.destination)

    def __call__(self, game: BatchedGame, mask: np.ndarray | None = None) -> np.ndarray:
        """Phi of every agent of the games where ``mask`` is True (others 0), shape (B, 1+k)."""
        phi = np.zeros((game.batch_size, game.n_agents), np.float32)
        phi[:, 0] = -np.abs(game.positions[:, 0] - self._destination).max(axis=1)
        if mask is not None:
            phi[~mask] = 0
        return phi
