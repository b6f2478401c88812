"""The rules of the formation game (``docs/GAME.md``, rules v2), stepping a batch of games at once.

This is the only implementation of the rules: the PettingZoo and RLlib views, the planner's
checks and the training rollouts all step this class. State and per-step results live in numpy
arrays allocated once; ``step`` writes into them in place.

Agent index 0 is the leader, 1..k the followers. Arrays:

- ``positions``        (B, 1+k, 2) int32  row, col of each agent
- ``obstacle_rows``    (B, O) int32       never change
- ``obstacle_cols``    (B, O) int32
- ``obstacle_dirs``    (B, O) int32       -1 or +1 (sign of the velocity)
- ``obstacle_speeds``  (B, O) int32       |velocity|, cells per step
- ``steps``            (B,) int32         steps taken in the current episode

and after each step: ``collided`` (B, 1+k), ``formation_kept``, ``reached``, ``terminated``,
``truncated``, ``success`` (B,) bool, ``distances`` (B, k) float (follower to leader, cells),
``rewards`` (B, 1+k) float32.
"""

from __future__ import annotations

import numpy as np

from formation.config import ConfigError, GameConfig
from formation.game.scenario import Scenario, parse_scenario

# Action index -> (d_row, d_col): F, FL, FR, S.
ACTION_NAMES = ("F", "FL", "FR", "S")
# Cells within Euclidean distance <= 1 of a cell, on the integer grid: the collision zone.
COLLISION_OFFSETS = np.array([[0, 0], [-1, 0], [1, 0], [0, -1], [0, 1]], dtype=np.int32)
MOVES = np.array([[-1, 0], [-1, -1], [-1, 1], [0, 0]], dtype=np.int32)


def joint_mask_bits(masks: np.ndarray) -> np.ndarray:
    """(N, leader's move, follower's move) bools of (N,) bit masks of joint actions of a leader and one follower:
    bit ``4 * leader's move + follower's move``."""
    moves = len(MOVES)
    return ((np.asarray(masks)[:, None] >> np.arange(moves * moves)) & 1).astype(bool).reshape(-1, moves, moves)


class BatchedGame:
    """``batch_size`` independent games under one config, stepped together."""

    def __init__(self, config: GameConfig, batch_size: int = 1, seed: int | None = None):
        if batch_size < 1:
            raise ConfigError(f"batch_size: {batch_size} is not allowed; allowed: an integer >= 1")
        self.config = config
        self.batch_size = B = batch_size
        self.n_agents = A = 1 + config.n_followers
        self.rng = np.random.default_rng(seed)
        H, W = config.height, config.width
        self._upper = np.array([H - 1, W - 1], dtype=np.int32)
        self._obstacle_band_rows = np.array(config.obstacle_rows, dtype=np.int32)
        self._dest_col = config.destination[1]
        # Formation and distance depend only on the squared distance: exact lookup tables.
        d2 = np.arange(H * H + W * W + 1)
        dist = np.sqrt(d2)
        self._distance_of = dist
        self._kept_of = (dist > config.d_min) & (dist < config.d_max)
        self._apart_of = dist > config.d_min
        pairs = [(i, j) for i in range(1, A) for j in range(i + 1, A)]
        self._pair_i = np.array([p[0] for p in pairs], dtype=np.intp)
        self._pair_j = np.array([p[1] for p in pairs], dtype=np.intp)

        self.positions = np.zeros((B, A, 2), np.int32)
        self.steps = np.zeros(B, np.int32)
        self.collided = np.zeros((B, A), bool)
        self.formation_kept = np.ones(B, bool)
        self.reached = np.zeros(B, bool)
        self.terminated = np.zeros(B, bool)
        self.truncated = np.zeros(B, bool)
        self.success = np.zeros(B, bool)
        self.distances = np.zeros((B, A - 1), np.float64)
        self.rewards = np.zeros((B, A), np.float32)
        self._move = np.zeros((B, A, 2), np.int32)
        self._d2 = np.zeros((B, A - 1), np.intp)
        self._diff = np.zeros((B, A - 1, 2), np.int32)
        self._ok = np.zeros((B, A - 1), bool)
        self._pair_d2 = np.zeros((B, len(pairs)), np.intp)
        self._pair_ok = np.zeros((B, len(pairs)), bool)
        self._any_collided = np.zeros(B, bool)
        self._formation_reward = np.zeros(B, np.float32)
        self._allocate_obstacles(config.n_obstacles)

    # ------------------------------------------------------------------ state
    def _allocate_obstacles(self, n_obstacles: int) -> None:
        B, A, O = self.batch_size, self.n_agents, n_obstacles
        self.n_obstacles = O
        self.obstacle_rows = np.zeros((B, O), np.int32)
        self.obstacle_cols = np.zeros((B, O), np.int32)
        self.obstacle_dirs = np.ones((B, O), np.int32)
        self.obstacle_speeds = np.ones((B, O), np.int32)
        self._next_cols = np.zeros((B, O), np.int32)
        self._bounce = np.zeros((B, O), bool)
        self._row_gap = np.zeros((B, A, O), np.int32)
        self._gap = np.zeros((B, A, O), np.int32)
        self._touch = np.zeros((B, A, O), bool)
        self._hit = np.zeros((B, A, O), bool)
        self._moving: list[np.ndarray] = []

    def _after_obstacles_change(self) -> None:
        """Recompute which obstacles still move at each sub-step (speed > sub-step index)."""
        top = int(self.obstacle_speeds.max()) if self.obstacle_speeds.size else 0
        self._moving = [self.obstacle_speeds > s for s in range(top)]

    def reset(self, seed: int | None = None, mask: np.ndarray | None = None) -> None:
        """Start random games (docs/GAME.md, 'Entities') in the games where ``mask`` is True (all if None)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        if self.n_obstacles != self.config.n_obstacles:
            self._allocate_obstacles(self.config.n_obstacles)
            mask = None
        idx = np.arange(self.batch_size) if mask is None else np.flatnonzero(mask)
        n = len(idx)
        if n == 0:
            return
        cfg, rng, O = self.config, self.rng, self.n_obstacles
        leader, followers = cfg.starts
        self.positions[idx, 0] = leader
        self.positions[idx, 1:] = followers
        band = self._obstacle_band_rows
        self.obstacle_rows[idx] = band[np.argsort(rng.random((n, len(band))), axis=1)[:, :O]]
        self.obstacle_cols[idx] = rng.integers(0, cfg.width, size=(n, O))
        self.obstacle_speeds[idx] = rng.choice(np.asarray(cfg.obstacle_speeds), size=(n, O))
        self.obstacle_dirs[idx] = rng.choice(np.array([-1, 1]), size=(n, O))
        self._clear_flags(idx)
        self._after_obstacles_change()

    def load(self, scenarios: list, mask: np.ndarray | None = None) -> None:
        """Start the games where ``mask`` is True (all if None) from scenarios, one each, in order."""
        idx = np.arange(self.batch_size) if mask is None else np.flatnonzero(mask)
        if len(scenarios) != len(idx):
            raise ConfigError(f"scenario: got {len(scenarios)} scenarios for {len(idx)} games")
        parsed = [parse_scenario(s, self.config) for s in scenarios]
        counts = {len(s.obstacles) for s in parsed}
        if len(counts) > 1 or (counts and counts != {self.n_obstacles}):
            if len(counts) == 1 and len(idx) == self.batch_size:
                self._allocate_obstacles(counts.pop())
            else:
                raise ConfigError(f"scenario: every game of a batch needs the same number of obstacles "
                                  f"({self.n_obstacles} here)")
        for i, s in zip(idx, parsed):
            self.positions[i, 0] = s.leader
            self.positions[i, 1:] = s.followers
            if self.n_obstacles:
                obstacles = np.array(s.obstacles, dtype=np.int32).reshape(-1, 3)
                self.obstacle_rows[i] = obstacles[:, 0]
                self.obstacle_cols[i] = obstacles[:, 1]
                self.obstacle_dirs[i] = np.sign(obstacles[:, 2])
                self.obstacle_speeds[i] = np.abs(obstacles[:, 2])
        self._clear_flags(idx)
        self._after_obstacles_change()

    def _clear_flags(self, idx: np.ndarray) -> None:
        self.steps[idx] = 0
        for flags in (self.collided, self.reached, self.terminated, self.truncated, self.success):
            flags[idx] = False
        self.formation_kept[idx] = True
        self.rewards[idx] = 0
        leader = self.positions[idx, :1].astype(np.int64)
        diff = self.positions[idx, 1:] - leader
        self.distances[idx] = np.sqrt((diff.astype(np.float64) ** 2).sum(-1))

    def scenario(self, i: int = 0) -> Scenario:
        """Game ``i``'s present state; ``load([it])`` reproduces it and its future exactly."""
        p = self.positions[i].tolist()
        velocities = (self.obstacle_dirs[i] * self.obstacle_speeds[i]).tolist()
        obstacles = zip(self.obstacle_rows[i].tolist(), self.obstacle_cols[i].tolist(), velocities)
        return Scenario(tuple(p[0]), tuple(map(tuple, p[1:])), tuple(obstacles))

    # ------------------------------------------------------------------ the rules
    def step(self, actions: np.ndarray) -> None:
        """Apply one joint action per game, ``actions`` (B, 1+k) ints in 0..3 (docs/GAME.md, 'One step')."""
        pos = self.positions
        # 1. Both agents move at once, clamped to the board.
        np.take(MOVES, actions, axis=0, out=self._move)
        np.add(pos, self._move, out=pos)
        np.clip(pos, 0, self._upper, out=pos)
        rows, cols = pos[:, :, 0], pos[:, :, 1]
        # 2.-3. Obstacles sweep |v| unit sub-steps; an agent collides when within distance <= 1
        # of any cell an obstacle reached after a sub-step. On integer cells that is
        # |d_row| + |d_col| <= 1, and |d_row| is fixed because obstacles keep their rows.
        hit = self._hit
        hit.fill(False)
        if self.n_obstacles:
            np.subtract(rows[:, :, None], self.obstacle_rows[:, None, :], out=self._row_gap)
            np.abs(self._row_gap, out=self._row_gap)
            for obstacle_cols in self.sweep_obstacles():
                np.subtract(cols[:, :, None], obstacle_cols[:, None, :], out=self._gap)
                np.abs(self._gap, out=self._gap)
                np.add(self._gap, self._row_gap, out=self._gap)
                np.less_equal(self._gap, 1, out=self._touch)
                np.logical_or(hit, self._touch, out=hit)
        np.any(hit, axis=2, out=self.collided)
        # 4. Formation: every follower strictly between d_min and d_max of the leader, and
        # (with several followers) every two followers more than d_min apart.
        np.subtract(pos[:, 1:], pos[:, :1], out=self._diff)
        np.square(self._diff, out=self._diff)
        np.sum(self._diff, axis=2, out=self._d2)
        np.take(self._distance_of, self._d2, out=self.distances)
        np.take(self._kept_of, self._d2, out=self._ok)
        np.all(self._ok, axis=1, out=self.formation_kept)
        if len(self._pair_i):
            gap = pos[:, self._pair_i] - pos[:, self._pair_j]
            np.sum(gap * gap, axis=2, out=self._pair_d2)
            np.take(self._apart_of, self._pair_d2, out=self._pair_ok)
            self.formation_kept &= self._pair_ok.all(axis=1)
        # 5. Reach: the leader stands on the destination.
        np.equal(rows[:, 0], 0, out=self.reached)
        self.reached &= cols[:, 0] == self._dest_col
        # Rewards: formation term for everyone, own collision term, the leader's reach bonus.
        cfg = self.config
        np.copyto(self._formation_reward, cfg.reward_formation_broken)
        np.copyto(self._formation_reward, cfg.reward_formation_kept, where=self.formation_kept)
        r = self.rewards
        np.multiply(self.collided, cfg.reward_collision, out=r)
        r += self._formation_reward[:, None]
        r[:, 0] += self.reached * np.float32(cfg.reward_reach)
        # End of the episode, for both agents at once.
        np.any(self.collided, axis=1, out=self._any_collided)
        np.logical_or(self.reached, self._any_collided, out=self.terminated)
        self.terminated |= ~self.formation_kept
        self.steps += 1
        np.greater_equal(self.steps, cfg.max_steps, out=self.truncated)
        self.truncated &= ~self.terminated
        np.logical_and(self.reached, self.formation_kept, out=self.success)
        self.success &= ~self._any_collided

    def sweep_obstacles(self):
        """Rule 2 alone: move every obstacle |v| unit sub-steps, yielding ``obstacle_cols`` after
        each sub-step (the cells an obstacle 'reached', for the collision rule). It yields the
        live array, overwritten by the next sub-step: copy what you keep."""
        for moving in self._moving:
            self._sub_step(moving)
            yield self.obstacle_cols

    def _sub_step(self, moving: np.ndarray) -> None:
        """One unit sub-step: reverse before a move that would leave [0, W-1], then move."""
        nxt = self._next_cols
        np.add(self.obstacle_cols, self.obstacle_dirs, out=nxt)
        # A negative column viewed as unsigned is huge, so one comparison finds both edges.
        np.greater(nxt.view(np.uint32), self.config.width - 1, out=self._bounce)
        self._bounce &= moving
        np.negative(self.obstacle_dirs, out=self.obstacle_dirs, where=self._bounce)
        np.add(self.obstacle_cols, self.obstacle_dirs, out=self.obstacle_cols, where=moving)

    @property
    def done(self) -> np.ndarray:
        return self.terminated | self.truncated
