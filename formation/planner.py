"""The clairvoyant planner: the exact shortest path of joint actions from a scenario to success.

The obstacles move on their own, whatever the leader and followers do, so the whole future of
the board is known at reset. For every step ``t`` the *collision zone* ``Z_t`` is the set of
cells within distance <= 1 of any cell an obstacle reached after one of its unit sub-steps of
step ``t`` (spec rules 2-3); an agent collides at step ``t`` exactly when it stands in ``Z_t``.
The zones come from the game itself: the scenario is loaded into a ``BatchedGame`` and
``sweep_obstacles`` is run once per step, so the obstacle motion exists in one place only.

What is left is a shortest-path problem on a time-expanded graph. A *joint state* is the cells
of the leader and of every follower; *layer* ``t`` holds the joint states the team can be in
after ``t`` steps with every step so far non-terminal (nobody in a collision zone, formation
kept, the leader not yet on the destination). Layer ``t + 1`` comes from trying all ``4 ** (1+k)``
joint actions on every state of layer ``t`` and keeping the moves that land outside ``Z_{t+1}``
with the formation kept. The first layer in which the leader stands on the destination gives
the shortest path (a breadth-first search), rebuilt from parent pointers.

Two things keep it fast:

- **Deadline pruning.** The leader needs at least ``max(row, |col - destination col|)`` more
  steps (one row and one column per step at most), so a search for paths of at most ``T``
  steps drops every state whose leader cannot arrive by ``T``. The search is first run with
  ``T`` = the lower bound from the start, which almost always succeeds (on random scenarios of
  settings 1-4 it nearly always does); if it fails, ``T`` grows (lower bound + 4, + 16, + 64, ...
  up to ``max_steps``). Each search finds every path of length <= ``T``, and the deadlines grow,
  so the first path found is a shortest one overall. A search costs roughly in proportion to its
  slack, so the failed ones add about a third to the last one.
- **Deduplication per layer.** Many move orders lead to the same joint state; each layer keeps
  one copy, found with a dense array indexed by a state code (the leader's cell and each
  follower's offset from it, which the formation keeps small), or ``np.unique`` where that code
  space would be too large.

Everything is vectorised over the states of a layer with numpy.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from formation.config import ConfigError, GameConfig
from formation.game import COLLISION_OFFSETS, MOVES, BatchedGame, Scenario, parse_scenario

__all__ = ["lower_bound", "shortest_first_moves", "shortest_path"]

N_ACTIONS = len(MOVES)
# Largest state-code space deduplicated with a dense array (int32 entries); above it, np.unique.
DENSE_CODES_LIMIT = 1 << 23


def lower_bound(scenario: dict | Scenario, config: GameConfig | None = None) -> int:
    """Steps the leader needs to reach the destination ignoring obstacles and followers:
    its rows to go, or its columns to go if more (a step changes each by at most one)."""
    config = config or GameConfig()
    leader = parse_scenario(scenario, config).leader
    return _steps_to_go(leader, config)


def shortest_path(scenario: dict | Scenario, setting: int | None = 1, *, config: GameConfig | None = None,
                  **overrides: Any) -> list[tuple[int, ...]] | None:
    """The shortest list of joint actions ``(leader action, follower action(s))`` that ends in
    success within ``max_steps``, every earlier step non-terminal; ``None`` if there is none.

    The game's rules come from ``config``, or else from ``GameConfig.from_setting(setting,
    **overrides)``. Actions are indices into ``formation.game.MOVES`` (0 F, 1 FL, 2 FR, 3 S).
    """
    if config is None:
        config = GameConfig.from_setting(setting, **overrides)
    elif overrides:
        raise ConfigError(f"config: give either config= or setting overrides, not both "
                          f"(got {', '.join(sorted(overrides))})")
    return _first_found(_search, parse_scenario(scenario, config), config)


def shortest_first_moves(scenario: dict | Scenario, *, config: GameConfig) -> tuple[int, list[tuple[int, ...]]] | None:
    """The length of a shortest successful path and every joint action that starts one (in index
    order), from one search; ``None`` if no path ends in success within ``max_steps``. At most
    two followers (the first moves of a layer's states are kept as 64-bit masks)."""
    parsed = parse_scenario(scenario, config)
    n_agents = 1 + len(parsed.followers)
    if N_ACTIONS ** n_agents > 64:
        raise ConfigError(f"n_followers: {n_agents - 1} is not allowed here; allowed: 1 or 2")
    found = _first_found(_search_first_moves, parsed, config)
    if found is None:
        return None
    length, mask = found
    return length, [_split(j, n_agents) for j in range(N_ACTIONS ** n_agents) if (mask >> j) & 1]


def shortest_path_counts(scenario: dict | Scenario, *,
                         config: GameConfig) -> tuple[int, dict[tuple[int, ...], float]] | None:
    """The length of a shortest successful path and, for every joint action that starts one, how
    many shortest successful paths start with it; ``None`` if no path ends in success within
    ``max_steps``. Paths are sequences of joint actions (two that visit the same states by other
    moves count twice)."""
    parsed = parse_scenario(scenario, config)
    n_agents = 1 + len(parsed.followers)
    found = _first_found(functools.partial(_search_first_moves, count=True), parsed, config)
    if found is None:
        return None
    length, counts = found
    return length, {_split(j, n_agents): float(counts[j]) for j in np.flatnonzero(counts)}


def _first_found(search, parsed: Scenario, config: GameConfig):
    """Run ``search(board, zones, start, deadline)`` with growing deadlines; its first answer."""
    start = (parsed.leader, *parsed.followers)
    bound = _steps_to_go(parsed.leader, config)
    if bound > config.max_steps:
        return None
    board = _Board(config)
    future = _ObstacleFuture(config, parsed, board)
    for deadline in _deadlines(bound, config.max_steps):
        found = search(board, future.zones(deadline), start, deadline)
        if found is not None:
            return found
    return None


def _steps_to_go(leader: tuple[int, int], config: GameConfig) -> int:
    dest_row, dest_col = config.destination
    return max(leader[0] - dest_row, abs(leader[1] - dest_col))


def _deadlines(bound: int, max_steps: int) -> list[int]:
    """The lower bound first, then slack growing fourfold up to ``max_steps``."""
    deadlines, slack = [bound], 4
    while deadlines[-1] < max_steps:
        deadlines.append(min(bound + slack, max_steps))
        slack *= 4
    return deadlines


class _Board:
    """Lookup tables over the cells of the board; a cell is the integer ``row * W + col``."""

    def __init__(self, config: GameConfig):
        H, W = config.height, config.width
        self.height, self.width = H, W
        self.row, self.col = np.divmod(np.arange(H * W, dtype=np.int32), W)
        # next_cell[cell, action]: where an agent lands, clamped to the board (spec 'Actions').
        rows = np.clip(self.row[:, None] + MOVES[:, 0], 0, H - 1)
        cols = np.clip(self.col[:, None] + MOVES[:, 1], 0, W - 1)
        self.next_cell = (rows * W + cols).astype(np.int32)
        dest_row, dest_col = config.destination
        self.destination = dest_row * W + dest_col
        self.steps_to_go = np.maximum(self.row - dest_row, np.abs(self.col - dest_col))
        # Formation by squared distance, computed as the game computes it.
        distance = np.sqrt(np.arange((H - 1) ** 2 + (W - 1) ** 2 + 1))
        self.kept_of = (distance > config.d_min) & (distance < config.d_max)
        self.apart_of = distance > config.d_min
        # A follower in formation is at most `reach` rows and columns from the leader.
        reach = max(math.ceil(config.d_max) - 1, 0)
        self.reach_rows, self.reach_cols = min(reach, H - 1), min(reach, W - 1)
        self.n_offsets = (2 * self.reach_rows + 1) * (2 * self.reach_cols + 1)


class _ObstacleFuture:
    """The collision zones ``Z_1, Z_2, ...`` of one scenario, computed by the game as needed."""

    def __init__(self, config: GameConfig, scenario: Scenario, board: _Board):
        self.board = board
        self.game = BatchedGame(config, batch_size=1)
        self.game.load([scenario])
        self.obstacle_rows = self.game.obstacle_rows[0].copy()
        # _zones[t, cell]: is the cell in Z_t (row 0 stands for the reset and stays empty).
        self._zones = np.zeros((1, board.height * board.width), bool)

    def zones(self, n_steps: int) -> np.ndarray:
        """``(n_steps + 1, H * W)`` bool: the collision zone of every step up to ``n_steps``."""
        known = len(self._zones) - 1
        if n_steps > known:
            self._zones = np.concatenate([self._zones, self._sweep(n_steps - known)])
        return self._zones[: n_steps + 1]

    def _sweep(self, n_steps: int) -> np.ndarray:
        board = self.board
        zones = np.zeros((n_steps, board.height * board.width), bool)
        if self.game.n_obstacles == 0:
            return zones
        # reached[t, s, o]: the column of obstacle o after sub-step s of step t.
        reached = np.array([[cols[0].copy() for cols in self.game.sweep_obstacles()]
                            for _ in range(n_steps)], dtype=np.int32)
        if reached.size == 0:
            return zones
        rows = self.obstacle_rows[None, None, :, None] + COLLISION_OFFSETS[:, 0]
        cols = reached[..., None] + COLLISION_OFFSETS[:, 1]
        rows = np.broadcast_to(rows, cols.shape)
        step = np.broadcast_to(np.arange(n_steps)[:, None, None, None], cols.shape)
        on_board = (rows >= 0) & (rows < board.height) & (cols >= 0) & (cols < board.width)
        zones[step[on_board], rows[on_board] * board.width + cols[on_board]] = True
        return zones


def _search(board: _Board, zones: np.ndarray, start: tuple, deadline: int) -> list[tuple[int, ...]] | None:
    """Breadth-first search over time layers for a success within ``deadline`` steps."""
    n_agents = len(start)
    layer = np.array([[r * board.width + c for r, c in start]], dtype=np.int32)  # (states, agents)
    parents: list[np.ndarray] = []  # per layer t >= 1: index of each state's parent in layer t-1
    joint_actions: list[np.ndarray] = []  # and the joint action that led there
    dedupe = _Deduplicator(board, n_agents)
    for t in range(deadline):
        parent, joint, cells = _successors(board, layer, zones[t + 1], deadline - t - 1)
        success = np.flatnonzero(cells[:, 0] == board.destination)
        if len(success):
            first = success[0]
            return _rebuild(parents, joint_actions, int(parent[first]), int(joint[first]), n_agents)
        keep = dedupe(cells)
        if len(keep) == 0:
            return None
        layer = cells[keep]
        parents.append(parent[keep])
        joint_actions.append(joint[keep])
    return None


def _search_first_moves(board: _Board, zones: np.ndarray, start: tuple, deadline: int,
                        count: bool = False) -> tuple[int, Any] | None:
    """``_search`` that keeps, for every state of a layer, the set of first joint actions of the
    paths reaching it (a bit mask, merged over duplicates): ``(length, mask)`` of the first
    layer with a success, the mask over all successes in it. ``count``: instead of the mask, how
    many paths reach each state by each first joint action, ``(length, counts)`` with ``counts``
    the shortest successful paths that start with each joint action (by joint action index)."""
    layer = np.array([[r * board.width + c for r, c in start]], dtype=np.int32)
    n_joint = N_ACTIONS ** len(start)
    firsts = None  # per state of the layer: mask (or counts) of first joint actions (None at the start)
    dedupe = _Deduplicator(board, len(start))
    for t in range(deadline):
        parent, joint, cells = _successors(board, layer, zones[t + 1], deadline - t - 1)
        if firsts is not None:
            carried = firsts[parent]
        elif count:
            carried = np.zeros((len(joint), n_joint))
            carried[np.arange(len(joint)), joint] = 1.0
        else:
            carried = np.uint64(1) << joint.astype(np.uint64)
        success = cells[:, 0] == board.destination
        if success.any():
            if count:
                return t + 1, carried[success].sum(axis=0)
            return t + 1, int(np.bitwise_or.reduce(carried[success]))
        if len(cells) == 0:
            return None
        codes = dedupe._codes(cells)
        unique, inverse = np.unique(codes, return_inverse=True)
        if count:
            firsts = np.zeros((len(unique), n_joint))
            np.add.at(firsts, inverse, carried)
        else:
            firsts = np.zeros(len(unique), np.uint64)
            np.bitwise_or.at(firsts, inverse, carried)
        keep = np.zeros(len(unique), np.intp)
        keep[inverse] = np.arange(len(cells))  # one copy of each state (any: they are equal)
        layer = cells[keep]
    return None


def _successors(board: _Board, layer: np.ndarray, zone: np.ndarray, steps_left: int):
    """Every allowed move from ``layer``: the parent state's index, the joint action, and the
    cells the agents land on, ``(moves, agents)``."""
    n_agents = layer.shape[1]
    landing, allowed = _expand(board, layer, zone, steps_left)
    parent, joint = np.divmod(np.flatnonzero(allowed), N_ACTIONS ** n_agents)
    actions = [(joint // N_ACTIONS ** (n_agents - 1 - i)) % N_ACTIONS for i in range(n_agents)]
    cells = np.stack([landing[parent, i, a] for i, a in enumerate(actions)], axis=1)
    return parent, joint, cells


def _expand(board: _Board, layer: np.ndarray, zone: np.ndarray, steps_left: int):
    """Every joint action from every state of ``layer``: ``landing[state, agent, action]`` (the
    cell an agent lands on) and ``allowed[state, a_leader, a_follower, ...]`` (no collision,
    formation kept, and the leader can still reach the destination in ``steps_left`` steps)."""
    n, n_agents = layer.shape
    landing = board.next_cell[layer]  # (n, agents, actions)
    safe = ~zone[landing]
    safe[:, 0] &= board.steps_to_go[landing[:, 0]] <= steps_left

    def along(values: np.ndarray, agent: int) -> np.ndarray:
        """Put an agent's per-action values on its own axis of the joint-action grid."""
        shape = [n] + [1] * n_agents
        shape[1 + agent] = N_ACTIONS
        return values.reshape(shape)

    allowed = along(safe[:, 0], 0)
    for agent in range(1, n_agents):
        allowed = allowed & along(safe[:, agent], agent)
    rows, cols = board.row[landing], board.col[landing]

    def squared_distance(a: int, b: int) -> np.ndarray:
        d_row = along(rows[:, a], a) - along(rows[:, b], b)
        d_col = along(cols[:, a], a) - along(cols[:, b], b)
        return d_row * d_row + d_col * d_col

    for follower in range(1, n_agents):
        allowed = allowed & board.kept_of[squared_distance(0, follower)]
    for i in range(1, n_agents):
        for j in range(i + 1, n_agents):
            allowed = allowed & board.apart_of[squared_distance(i, j)]
    return landing, np.broadcast_to(allowed, (n,) + (N_ACTIONS,) * n_agents)


class _Deduplicator:
    """Keeps one of each joint state in a layer. The code of a state is its leader's cell and
    each follower's offset from the leader (bounded, since every stored state keeps formation)."""

    def __init__(self, board: _Board, n_agents: int):
        self.board = board
        self.n_codes = board.height * board.width * board.n_offsets ** (n_agents - 1)
        self.mark = np.empty(self.n_codes, np.int32) if self.n_codes <= DENSE_CODES_LIMIT else None

    def __call__(self, cells: np.ndarray) -> np.ndarray:
        """Indices of the first (dense: some) copy of each distinct state among ``cells``."""
        codes = self._codes(cells)
        if self.mark is None:
            return np.sort(np.unique(codes, return_index=True)[1])
        order = np.arange(len(codes), dtype=np.int32)
        self.mark[codes] = order
        return np.flatnonzero(self.mark[codes] == order)

    def _codes(self, cells: np.ndarray) -> np.ndarray:
        b = self.board
        leader = cells[:, :1]
        d_row = b.row[cells[:, 1:]] - b.row[leader] + b.reach_rows
        d_col = b.col[cells[:, 1:]] - b.col[leader] + b.reach_cols
        offsets = d_row * (2 * b.reach_cols + 1) + d_col
        codes = leader[:, 0].astype(np.int64)
        for i in range(offsets.shape[1]):
            codes = codes * b.n_offsets + offsets[:, i]
        return codes


def _rebuild(parents: list[np.ndarray], joint_actions: list[np.ndarray], parent: int, joint: int,
             n_agents: int) -> list[tuple[int, ...]]:
    """Walk the parent pointers back from the last move to the start."""
    joints = [joint]
    for layer in range(len(parents) - 1, -1, -1):
        joints.append(int(joint_actions[layer][parent]))
        parent = int(parents[layer][parent])
    joints.reverse()
    return [_split(joint, n_agents) for joint in joints]


def _split(joint: int, n_agents: int) -> tuple[int, ...]:
    """A joint action index (leader's action the most significant base-4 digit) as a tuple."""
    return tuple((joint // N_ACTIONS ** (n_agents - 1 - i)) % N_ACTIONS for i in range(n_agents))
