"""A safety shield for a trained team: keep its joint move unless that move leads, within ``horizon``
steps, into a state from which every continuation collides or breaks the formation; then play the
move the networks like best among the safe ones.

The shield acts from the same observation as the networks (the stacked screens or grids) and knows
only the game's rules. It reads the state off the two newest frames (``read_states``): the cells of
the leader, the follower and the obstacles, and each obstacle's velocity from where it was one frame
before, under the game's rule of motion (docs/GAME.md, 'One step': an obstacle bounces between columns
0 and W-1 like a ball, a constant motion on a circle of 2(W-1) places folded in two). Where a frame
does not tell a velocity (an episode's first screen, repeated in the stack; a row holding more than
one obstacle), every velocity of the config's speeds is a reading of its own. Each reading becomes
a scenario, and the planner (``surviving_first_moves_many``, which steps obstacles with the game
itself) lists the joint moves that start ``horizon`` steps free of failure; a move is safe when it
is on that list for the most readings. This is "shielding" (Alshiekh et al. 2018, "Safe reinforcement learning via
shielding"): the networks still choose where the team goes; the shield only vetoes moves that are
already lost. It is not part of the paper's method (docs/RESULTS.md reports the team with and
without it).
"""

from __future__ import annotations

import itertools

import numpy as np

from formation.config import ConfigError, GameConfig
from formation.game.render import GRID_PLANES, cell_pixel_bounds
from formation.game.scenario import parse_scenario
from formation.planner import N_ACTIONS, surviving_first_moves_many

N_JOINT = N_ACTIONS * N_ACTIONS
# A frame whose readings would number more than this gets no veto (every move allowed).
MAX_READINGS = 256


def obstacle_readings(col: int, col_before: int | None, width: int, speeds: tuple[int, ...]) -> list[int]:
    """The velocities (signed) an obstacle now at ``col`` may have, given its column one step before
    (None: unknown): those of the rule of motion that carry ``col_before`` to ``col`` in one step,
    every velocity if none does or ``col_before`` is unknown. At a wall both directions move alike,
    so only one is kept there."""
    period = max(2 * (width - 1), 1)

    def fold(place: int) -> int:
        return period - place if place > width - 1 else place

    found = []
    for speed in speeds:
        for direction in (1, -1):
            if direction < 0 and col in (0, width - 1):
                continue  # at a wall the way back is the same motion
            place = col if direction > 0 else (period - col) % period
            if col_before is None or fold((place - speed) % period) == col_before:
                found.append(direction * speed)
    if not found:
        return obstacle_readings(col, None, width, speeds)
    return found


class FrameReader:
    """The cells of the leader, the followers and the obstacles on the frames of an observation stack
    (screens read one pixel per cell, or grids)."""

    def __init__(self, config: GameConfig):
        self.config = config
        self.screens = config.obs_type == "pixels"
        self.frame_channels = 3 if self.screens else len(GRID_PLANES)
        if self.screens:
            self.rows = cell_pixel_bounds(config.height, config.screen_size)[:, 0]
            self.cols = cell_pixel_bounds(config.width, config.screen_size)[:, 0]

    def frames(self, obs: np.ndarray) -> int:
        return obs.shape[-1] // self.frame_channels

    def kinds(self, obs: np.ndarray, back: int) -> dict[str, np.ndarray]:
        """(H, W) bool planes of the frame ``back`` frames before the newest: "leader", "followers",
        "obstacles"."""
        start = obs.shape[-1] - (back + 1) * self.frame_channels
        frame = obs[..., start:start + self.frame_channels]
        if self.screens:
            frame = frame[self.rows][:, self.cols]
            red, green, blue = (frame[..., i] > 127 for i in range(3))
            return {"leader": blue & ~red & ~green, "followers": green & ~red & ~blue,
                    "obstacles": red & ~green & ~blue}
        planes = {name: frame[..., i] > 0 for i, name in enumerate(GRID_PLANES)}
        return {"leader": planes["leader"], "followers": planes["followers"], "obstacles": planes["obstacles"]}


def read_states(obs: np.ndarray, config: GameConfig, horizon: int, reader: FrameReader | None = None
                ) -> list[list[dict]] | None:
    """Every reading of the state one observation ``(h, w, c)`` shows, as scenarios; None where it
    shows no playable state (an agent missing, the game over) or has more than ``MAX_READINGS``
    readings. Obstacles that cannot come near the team within ``horizon`` steps (agents move one row
    up at most per step, never down) keep one velocity: theirs does not change what is safe."""
    reader = reader or FrameReader(config)
    now = reader.kinds(obs, 0)
    before = reader.kinds(obs, 1) if reader.frames(obs) > 1 else None
    leader = np.argwhere(now["leader"])
    followers = np.argwhere(now["followers"])
    if len(leader) != 1 or len(followers) != config.n_followers:
        return None
    agent_rows = [int(leader[0, 0]), *followers[:, 0].tolist()]
    near_top, near_bottom = min(agent_rows) - horizon - 1, max(agent_rows) + 1
    moved = before is not None and bool((before["obstacles"] != now["obstacles"]).any())
    per_obstacle: list[list[list[int]]] = []
    for row in np.unique(np.nonzero(now["obstacles"])[0]).tolist():
        cols = np.flatnonzero(now["obstacles"][row]).tolist()
        cols_before = np.flatnonzero(before["obstacles"][row]).tolist() if before is not None else []
        known = moved and len(cols) == 1 and len(cols_before) == 1
        for col in cols:
            velocities = obstacle_readings(col, cols_before[0] if known else None, config.width,
                                           config.obstacle_speeds)
            if not near_top <= row <= near_bottom:
                velocities = velocities[:1]
            per_obstacle.append([[row, col, v] for v in velocities])
    if np.prod([len(options) for options in per_obstacle], dtype=float) > MAX_READINGS:
        return None
    team = {"leader": leader[0].tolist()}
    if config.n_followers == 1:
        team["follower"] = followers[0].tolist()
    else:
        team["followers"] = followers.tolist()
    return [{**team, "obstacles": list(obstacles)} for obstacles in itertools.product(*per_obstacle)]


class Shield:
    """The joint moves a team may play: safe ones only, where the observation tells (see the module)."""

    def __init__(self, config: GameConfig, horizon: int):
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ConfigError(f"shield: {horizon!r} is not allowed; allowed: an integer >= 1 (steps ahead)")
        if config.n_followers != 1:
            raise ConfigError(f"shield: n_followers {config.n_followers} is not allowed; allowed: 1 (followers "
                              "look alike on the screen)")
        self.config, self.horizon = config, horizon
        self.reader = FrameReader(config)

    def allowed(self, obs: np.ndarray) -> np.ndarray:
        """(N, leader's move, follower's move) bool for observations (N, h, w, c): the joint moves safe
        for the most readings of each state; all of them where none is safe or the state is unread."""
        n = len(obs)
        allowed = np.ones((n, N_JOINT), bool)
        scenarios, owner = [], []
        for i in range(n):
            try:  # a state the game refuses (overlapping cells, a broken formation) is a game already over
                readings = [parse_scenario(s, self.config) for s in read_states(obs[i], self.config, self.horizon,
                                                                                self.reader) or []]
            except ConfigError:
                continue
            scenarios.extend(readings)
            owner.extend([i] * len(readings))
        if scenarios:
            masks = np.zeros(len(scenarios), np.uint64)
            sizes = np.array([len(s.obstacles) for s in scenarios])
            for size in np.unique(sizes):  # a batch of the planner holds one number of obstacles
                group = np.flatnonzero(sizes == size)
                masks[group] = surviving_first_moves_many([scenarios[k] for k in group], config=self.config,
                                                          horizon=self.horizon)
            safe = ((masks[:, None] >> np.arange(N_JOINT, dtype=np.uint64)) & np.uint64(1)).astype(bool)
            votes = np.zeros((n, N_JOINT), np.int64)
            np.add.at(votes, np.asarray(owner), safe)
            best = votes.max(axis=1, keepdims=True)
            allowed = np.where(best > 0, votes == best, True)
        return allowed.reshape(n, N_ACTIONS, N_ACTIONS)


def shielded_moves(leader_q: np.ndarray, follower_q: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Joint moves (N, 2) from the leader's Q-values (N, 4), the follower's answers to each leader move
    (N, 4, 4: leader's move, own move) and the ``allowed`` joint moves (N, 4, 4): the greedy team's
    move where allowed; else the leader's greedy move if some answer of the follower's is allowed,
    with the follower's best allowed answer; else the leader's best move that has an allowed answer,
    and the follower's best allowed answer to it."""
    n = len(leader_q)
    rows = np.arange(n)
    answerable = allowed.any(axis=2)  # (N, 4): leader moves with some allowed answer
    greedy_leader = leader_q.argmax(1)
    leader = np.where(answerable[rows, greedy_leader], greedy_leader,
                      np.where(answerable, leader_q, -np.inf).argmax(1))
    answers = follower_q[rows, leader]
    follower = np.where(allowed[rows, leader], answers, -np.inf).argmax(1)
    return np.stack([leader, follower], axis=1)
