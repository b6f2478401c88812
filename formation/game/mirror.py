"""The game seen in a mirror: columns reversed (``c -> W-1-c``), obstacles' velocities negated, left and
right moves swapped. On a board whose destination is its middle column (an odd width) and whose screen
cells are laid out the same from either side, the mirrored game is the same game: the mirror of a state
plays out as the mirror of that state's play, and its screens are the screens flipped left to right
(``tests/test_mirror.py`` checks both). ``train.mirror`` uses this to learn from every replayed step's
mirror image too.
"""

from __future__ import annotations

import numpy as np

from formation.config import GameConfig
from formation.game.core import MOVES, joint_mask_bits
from formation.game.render import cell_pixel_bounds
from formation.game.scenario import Scenario

# each move's index -> the index of the same move seen in a mirror (F -> F, FL <-> FR, S -> S)
MIRRORED_MOVE = np.array([int(np.flatnonzero((MOVES == (dr, -dc)).all(1))[0]) for dr, dc in MOVES], np.int64)


def mirror_symmetric(config: GameConfig) -> str | None:
    """None where the game is its own mirror image; else why not, in a few words."""
    if config.destination[1] != config.width - 1 - config.destination[1]:
        return f"a board of odd width, whose destination is its middle column (not width {config.width})"
    if config.n_followers != 1:
        return f"one follower (not {config.n_followers}: a mirror would swap their places)"
    if config.obs_type == "pixels":
        edges = np.append(cell_pixel_bounds(config.width)[:, 0], 84)
        if not (edges[::-1] == 84 - edges).all():
            return f"screen cells laid out the same from either side (not so for width {config.width})"
    return None


def mirror_scenario(scenario: Scenario, config: GameConfig) -> Scenario:
    """``scenario`` seen in a mirror."""
    flip = config.width - 1
    return Scenario(leader=(scenario.leader[0], flip - scenario.leader[1]),
                    followers=tuple((r, flip - c) for r, c in scenario.followers),
                    obstacles=tuple((r, flip - c, -v) for r, c, v in scenario.obstacles))


def mirror_steps(sample: dict[str, np.ndarray], which: np.ndarray) -> dict[str, np.ndarray]:
    """A replay sample (``obs`` and ``next_obs`` as (N, H, W, C), ``actions`` and ``labels`` as (N, agents),
    optionally ``answers`` as (N, agents, moves), and ``accepted`` and ``safe`` as (N,) bit masks of joint
    actions of a leader and one follower; labels and answers -1 where none) with the steps ``which``
    (N bools) seen in a mirror; the others, and the rewards, discounts and weights, as they were. A new
    dict; the arrays given are not written to."""
    out = dict(sample)
    for key in ("obs", "next_obs"):
        frames = sample[key].copy()
        frames[which] = frames[which][:, :, ::-1]
        out[key] = frames
    for key in ("actions", "labels", "answers"):
        if key not in sample:
            continue
        moves = sample[key]
        if key == "answers":  # the answer to a leader's move is, in the mirror, the answer to the mirrored move
            moves = moves[..., MIRRORED_MOVE]
        mirrored = np.where(moves >= 0, MIRRORED_MOVE[np.clip(moves, 0, None)], moves).astype(moves.dtype)
        out[key] = np.where(which.reshape(-1, *[1] * (moves.ndim - 1)), mirrored, sample[key])
    for key in ("accepted", "safe"):  # joint-move bit masks
        if key in sample:
            out[key] = np.where(which, mirror_joint_masks(sample[key]), sample[key])
    return out


def mirror_joint_masks(masks: np.ndarray) -> np.ndarray:
    """Bit masks of joint actions (bit ``4 * leader's move + follower's move``) seen in a mirror: every
    joint action's moves mirrored."""
    mirrored = joint_mask_bits(masks)[:, MIRRORED_MOVE][:, :, MIRRORED_MOVE].reshape(len(masks), -1)
    return (mirrored.astype(np.int64) << np.arange(mirrored.shape[1])).sum(1).astype(masks.dtype)
