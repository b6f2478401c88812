"""The clairvoyant planner: the exact shortest path of joint actions from a scenario to success.

The obstacles move on their own, whatever the leader and followers do, so the whole future of
the board is known at reset. For every step ``t`` the *collision zone* ``Z_t`` is the set of
cells within distance <= 1 of any cell an obstacle reached after one of its unit sub-steps of
step ``t`` (docs/GAME.md, 'One step', rules 2-3); an agent collides at step ``t`` exactly when it
stands in ``Z_t``.
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

import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np

from formation.config import ConfigError, GameConfig
from formation.game import COLLISION_OFFSETS, MOVES, BatchedGame, Scenario, parse_scenario

__all__ = ["EXACT_FOLLOWERS", "FirstMovesAhead", "lower_bound", "paths_exist", "shortest_first_moves_many",
           "shortest_path", "steps_bound", "surviving_first_moves_many"]

N_ACTIONS = len(MOVES)
# The largest team searched exactly: 4 ** (1 + k) joint moves from every joint state. Three followers (256) took
# 27 s for one scenario of setting 1, four (1024) ran out of 24 GB; larger teams get ``steps_bound`` instead.
EXACT_FOLLOWERS = 2
# Largest state-code space deduplicated with a dense array (of indices); above it, np.unique.
DENSE_CODES_LIMIT = 1 << 23
# Largest scratch array of deduplication kept between searches (16 MB): 16 scenarios of a 50x50 board.
KEPT_MARKS = 1 << 21
# Largest move table (state codes x joint actions, int32 entries) the searches step layers with; above it
# (two followers on a large board), layers are stepped as cells.
MOVE_TABLE_LIMIT = 1 << 22


def lower_bound(scenario: dict | Scenario, config: GameConfig | None = None) -> int:
    """Steps the leader needs to reach the destination ignoring obstacles and followers:
    its rows to go, or its columns to go if more (a step changes each by at most one)."""
    config = config or GameConfig()
    return _steps_to_go(_parse(scenario, config).leader, config)


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
    if config.n_followers > EXACT_FOLLOWERS:
        raise ConfigError(f"n_followers: {config.n_followers} is too large a team for the planner's exact search "
                          f"({N_ACTIONS ** (1 + config.n_followers)} joint moves per state); allowed: 1 to "
                          f"{EXACT_FOLLOWERS}; formation.planner.steps_bound gives a lower bound for larger teams")
    return _first_found(parse_scenario(scenario, config), config)


def steps_bound(scenario: dict | Scenario, config: GameConfig) -> int | None:
    """The steps of a shortest successful path of ``scenario``'s team: exactly for teams of up to
    ``EXACT_FOLLOWERS`` followers; for larger teams a lower bound, the longest of the shortest paths of the
    leader with each follower alone (where they stand, among the same obstacles). A path of the team is a path
    of each such pair, whose rules are a part of the team's (fewer collisions, fewer distances to keep), so none
    is shorter. None where a pair has no path within ``max_steps``: neither has the team. (Sub-teams of two
    followers gave the same bound on 120 scenarios of settings 1, 2 and 4 with three, at 9-40 times the time.)"""
    parsed = parse_scenario(scenario, config)
    if config.n_followers <= EXACT_FOLLOWERS:
        path = _first_found(parsed, config)
        return None if path is None else len(path)
    pair = config.replace(n_followers=1, follower_starts=None)
    longest = 0
    for follower in parsed.followers:
        path = _first_found(Scenario(leader=parsed.leader, followers=(follower,), obstacles=parsed.obstacles), pair)
        if path is None:
            return None
        longest = max(longest, len(path))
    return longest


def shortest_first_moves_many(scenarios: Sequence[dict | Scenario], *, config: GameConfig,
                              max_steps: Sequence[int] | None = None, ahead: FirstMovesAhead | None = None
                              ) -> list[tuple[int, list[tuple[int, ...]]] | None]:
    """For every scenario, the length of a shortest successful path and every joint action that starts
    one (in index order); ``None`` where no path ends in success within ``max_steps[i]`` steps (default:
    ``config.max_steps`` for all). From searches over all the scenarios at once, one per deadline they
    share, so numpy's cost per call is paid once for the lot. At most two followers (the first moves of
    a layer's states are kept as 64-bit masks). With ``ahead`` (of the same config), the scenarios it
    knows are answered from it, and the states on the shortest paths found are added to it."""
    n_agents = _mask_agents(config)
    parsed = [_parse(s, config) for s in scenarios]
    found = _first_moves_many(parsed, config, max_steps, masks=True, ahead=ahead)
    return [None if f is None else (f[0], [_split(j, n_agents) for j in range(N_ACTIONS ** n_agents)
                                           if (f[1] >> j) & 1])
            for f in found]


def paths_exist(scenarios: Sequence[dict | Scenario], *, config: GameConfig,
                max_steps: Sequence[int] | None = None) -> np.ndarray:
    """Whether each scenario has a successful path of at most ``max_steps[i]`` steps (default:
    ``config.max_steps``): ``shortest_path(...) is not None`` for all of them, searched at once."""
    parsed = [_parse(s, config) for s in scenarios]
    limits = [config.max_steps] * len(parsed) if max_steps is None else [int(m) for m in max_steps]
    if len(limits) != len(parsed):
        raise ConfigError(f"max_steps: got {len(limits)} limits for {len(parsed)} scenarios")
    exist = np.zeros(len(parsed), bool)
    bounds = [_steps_to_go(p.leader, config) for p in parsed]
    tried = [i for i, (bound, limit) in enumerate(zip(bounds, limits)) if bound <= limit]
    if tried:  # a path found by a beam is a path: only the others need the full searches
        board = _board_of(config)
        tight = np.array([bounds[i] for i in tried])
        zones = _ObstacleFuture(config, [parsed[i] for i in tried], board).zones(int(tight.max()))
        starts = np.array([[r * board.width + c for r, c in (parsed[i].leader, *parsed[i].followers)] for i in tried],
                          np.int32)
        exist[tried] = _beam_exists(board, zones, starts, tight, BEAM_WIDTH)
    rest = [i for i in tried if not exist[i]]
    found = _first_moves_many([parsed[i] for i in rest], config, [limits[i] for i in rest], masks=False)
    exist[rest] = [f is not None for f in found]
    return exist


def surviving_first_moves_many(scenarios: Sequence[dict | Scenario], *, config: GameConfig,
                               horizon: int) -> np.ndarray:
    """For every scenario, the joint actions that start ``horizon`` steps free of collisions and
    formation breaks (or that reach the destination sooner, with every step up to it free of them),
    as ``(scenarios,)`` uint64 bit masks (bit ``joint index``, as ``shortest_first_moves_many``'s
    joint actions). No deadline: the leader need not head for the destination. At most two followers."""
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ConfigError(f"horizon: {horizon!r} is not allowed; allowed: an integer >= 1")
    return _first_moves_surviving(scenarios, config, np.full(len(scenarios), horizon))


def _first_moves_surviving(scenarios: Sequence[dict | Scenario], config: GameConfig, steps: np.ndarray,
                           shortcut: bool = True) -> np.ndarray:
    """The joint actions that start ``steps[i]`` steps free of failures or a success sooner, as bit
    masks. With ``shortcut``, the first moves that a lockstep continuation shows safe
    (``_lockstep_survivors``) are not searched: the search starts from the others alone."""
    _mask_agents(config)
    parsed = [_parse(s, config) for s in scenarios]
    safe = np.zeros(len(parsed), np.uint64)  # the result: per scenario, its surviving first joint actions
    if not parsed:
        return safe
    board = _board_of(config)
    zones = _ObstacleFuture(config, parsed, board).zones(int(steps.max()))
    layer = np.array([[r * board.width + c for r, c in (p.leader, *p.followers)] for p in parsed], np.int32)
    shown = _lockstep_survivors(board, zones, layer, steps) if shortcut else None
    if shown is not None:
        safe |= shown
    owner = np.arange(len(parsed))
    firsts = None  # per state of the layer: the first joint actions of the paths reaching it (a bit mask)
    layers = _Layers(board, layer)
    layer = layers.start
    n_cells = board.height * board.width
    for t in range(int(steps.max())):
        parent, joint, states = layers.successors(layer, zones[:, t + 1].reshape(-1), config.max_steps,
                                                  offset=owner * n_cells)
        owner = owner[parent]
        if firsts is None and shown is not None:  # the first moves shown safe already need no search
            unknown = (shown[owner] >> joint.astype(np.uint64)) & np.uint64(1) == 0
            parent, joint, states, owner = parent[unknown], joint[unknown], states[unknown], owner[unknown]
        carried = firsts[parent] if firsts is not None else np.uint64(1) << joint.astype(np.uint64)
        done = layers.arrived(states)  # a success ends the episode: nothing after it can fail
        done |= steps[owner] == t + 1
        np.bitwise_or.at(safe, owner[done], carried[done])
        states, owner, carried = states[~done], owner[~done], carried[~done]
        if len(states) == 0:
            break
        keep, inverse = layers.groups(states, owner)
        firsts = np.zeros(len(keep), np.uint64)
        np.bitwise_or.at(firsts, inverse, carried)
        layer, owner = states[keep], owner[keep]
    return safe


# States per scenario a layer of ``_beam_exists`` keeps.
BEAM_WIDTH = 16


def _beam_exists(board: _Board, zones: np.ndarray, starts: np.ndarray, deadlines: np.ndarray, width: int
                 ) -> np.ndarray:
    """Whether a beam search finds a success within ``deadlines[k]`` steps for each scenario (``zones[k]``,
    ``starts[k]``): ``_search_first_moves`` keeping at most ``width`` states of a scenario per layer, spread
    evenly over the layer's order. True proves a path; False proves nothing. Most ``paths_exist`` questions
    (a teacher's first-step hypotheses) have many paths, and one is found at a small part of the cost."""
    n_scenarios, n_cells = len(starts), board.height * board.width
    layers = _Layers(board, starts)
    layer, owner = layers.start, np.arange(n_scenarios)  # owner stays sorted: successors keep their parents' order
    found = np.zeros(n_scenarios, bool)
    for t in range(int(deadlines.max())):
        parent, _, states = layers.successors(layer, zones[:, t + 1].reshape(-1), deadlines[owner] - t - 1,
                                              offset=owner * n_cells)
        owner = owner[parent]
        success = layers.arrived(states)
        if success.any():
            found[owner[success]] = True
            playing = ~found[owner]
            states, owner = states[playing], owner[playing]
        if len(states) == 0:
            break
        keep, _ = layers.groups(states, owner, inverse=False)
        states, owner = states[keep], owner[keep]
        begins = np.searchsorted(owner, np.arange(n_scenarios))
        counts = np.diff(begins, append=len(owner))
        if counts.max() > width:
            stride = -(-counts // width)  # per scenario, keep every stride-th state
            rank = np.arange(len(owner)) - begins[owner]
            kept = rank % stride[owner] == 0
            states, owner = states[kept], owner[kept]
        layer = states
    return found


# the continuations ``_lockstep_survivors`` tries after a first move: every agent stay, forward, left, right
LOCKSTEP_CONTINUATIONS = (3, 0, 1, 2)


def _lockstep_survivors(board: _Board, zones: np.ndarray, starts: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Per scenario (``starts[k]``: its agents' cells, ``zones[k]`` its collision zones), the joint actions
    after which a lockstep continuation, every agent making the same move every step, stays free of
    collisions and breaks up to ``steps[k]`` steps in all (or reaches the destination sooner), as bit
    masks. Each such path exists, so each bit is a first move that survives; most of the safe first
    moves are found so, in a few array passes instead of a search."""
    n, n_agents = starts.shape
    joints = np.arange(N_ACTIONS ** n_agents)
    moves = [(joints // N_ACTIONS ** (n_agents - 1 - i)) % N_ACTIONS for i in range(n_agents)]
    first = np.stack([board.next_cell[starts[:, i][:, None], moves[i][None, :]] for i in range(n_agents)], axis=2)
    scenario = np.arange(n)[:, None, None]

    def fine(cells: np.ndarray, t: int) -> np.ndarray:
        """(n, joints): no agent in step t's collision zone, and the formation kept (as ``_expand`` checks)."""
        ok = ~zones[scenario, t, cells].any(axis=2)
        rows, cols = board.row[cells], board.col[cells]

        def squared(a: int, b: int) -> np.ndarray:
            return (rows[..., a] - rows[..., b]) ** 2 + (cols[..., a] - cols[..., b]) ** 2
        for f in range(1, n_agents):
            ok &= board.kept_of[squared(0, f)]
        for i in range(1, n_agents):
            for j in range(i + 1, n_agents):
                ok &= board.apart_of[squared(i, j)]
        return ok

    horizon = steps[:, None]
    alive = fine(first, 1)
    ended = alive & ((first[..., 0] == board.destination) | (horizon <= 1))
    survived = ended.copy()
    for move in LOCKSTEP_CONTINUATIONS:
        cells, live = first, alive & ~ended
        for t in range(2, int(steps.max()) + 1):
            if not live.any():
                break
            cells = board.next_cell[cells, move]
            live &= fine(cells, t)
            done = live & ((cells[..., 0] == board.destination) | (horizon <= t))
            survived |= done
            live &= ~done
    bits = np.uint64(1) << joints.astype(np.uint64)
    return np.bitwise_or.reduce(np.where(survived, bits, np.uint64(0)), axis=1)


# Scenario objects found valid, per the config fields parse_scenario checks them against.
_VALID: dict[tuple, Scenario] = {}


def _parse(scenario: dict | Scenario, config: GameConfig) -> Scenario:
    """``parse_scenario``, answered from the last few thousand ``Scenario`` objects it found valid: a teacher asks
    about each state several times a step (its labels, answers and safety labels), each time checked alike."""
    if not isinstance(scenario, Scenario):
        return parse_scenario(scenario, config)
    key = (scenario, config.height, config.width, config.n_followers, config.d_min, config.d_max)
    if key not in _VALID:
        if len(_VALID) >= 4096:
            _VALID.clear()
        _VALID[key] = parse_scenario(scenario, config)
    return _VALID[key]


def _mask_agents(config: GameConfig) -> int:
    """The team's size, where its joint actions fit a 64-bit mask (at most two followers)."""
    n_agents = 1 + config.n_followers
    if N_ACTIONS ** n_agents > 64:
        raise ConfigError(f"n_followers: {n_agents - 1} is not allowed here; allowed: 1 or 2")
    return n_agents


def _first_found(parsed: Scenario, config: GameConfig) -> list[tuple[int, ...]] | None:
    """Run ``_search`` with growing deadlines; its first path."""
    start = (parsed.leader, *parsed.followers)
    bound = _steps_to_go(parsed.leader, config)
    if bound > config.max_steps:
        return None
    board = _board_of(config)
    future = _ObstacleFuture(config, [parsed], board)
    for deadline in _deadlines(bound, config.max_steps):
        found = _search(board, future.zones(deadline)[0], start, deadline)
        if found is not None:
            return found
    return None


def _first_moves_many(parsed: list[Scenario], config: GameConfig, max_steps: Sequence[int] | None, masks: bool,
                      ahead: FirstMovesAhead | None = None) -> list[tuple[int, int | None] | None]:
    """``_search_first_moves`` of many scenarios with growing deadlines, as ``_first_found`` runs
    ``_search``: at each rung of the deadline ladders, one search over every scenario still
    unanswered whose ladder has that rung, each with its own deadline. ``ahead``: see
    ``shortest_first_moves_many`` (with ``masks`` only)."""
    limits = [config.max_steps] * len(parsed) if max_steps is None else [int(m) for m in max_steps]
    if len(limits) != len(parsed):
        raise ConfigError(f"max_steps: got {len(limits)} limits for {len(parsed)} scenarios")
    found: list[tuple[int, int | None] | None] = [None] * len(parsed)
    searched = list(range(len(parsed)))
    if ahead is not None:
        ahead.check(config)
        known = [ahead.get(p) for p in parsed]
        for i, answer in enumerate(known):  # the length is the shortest one: beyond the limit, no path within it
            found[i] = answer if answer is not None and answer[0] <= limits[i] else None
        searched = [i for i, answer in enumerate(known) if answer is None]
    bounds = [_steps_to_go(parsed[i].leader, config) for i in searched]
    ladders = [_deadlines(b, limits[i]) if b <= limits[i] else [] for b, i in zip(bounds, searched)]
    if not any(ladders):
        return found
    board = _board_of(config)
    future = _ObstacleFuture(config, [parsed[i] for i in searched], board)
    zones = future.zones(max(ladder[-1] for ladder in ladders if ladder))
    starts = np.array([[r * board.width + c for r, c in (parsed[i].leader, *parsed[i].followers)] for i in searched],
                      np.int32)
    for rung in range(max(len(ladder) for ladder in ladders)):
        members = [k for k, ladder in enumerate(ladders) if found[searched[k]] is None and rung < len(ladder)]
        if not members:
            break
        deadlines = np.array([ladders[k][rung] for k in members])
        trace = [] if ahead is not None and masks else None
        answers = _search_first_moves(board, zones[members, : deadlines.max() + 1], starts[members], deadlines, masks,
                                      trace)
        for k, answer in zip(members, answers):
            found[searched[k]] = answer
        if trace:
            ahead.add(_shortest_ahead(trace, len(members)), [future.obstacles(k) for k in members], answers)
    return found


class FirstMovesAhead:
    """What ``shortest_first_moves_many`` found about the states after its scenarios' starts, for later calls.

    The obstacles move on their own, so the obstacles of a state fix its whole future, and a state on a
    shortest path found from an earlier state with those obstacles then (an earlier state of the same
    episode, as a rollout's next states mostly are) needs no search of its own: its shortest paths are
    the rest of those paths, of the length left, and its first moves their next steps. Kept per obstacles,
    for the last ``capacity`` obstacle states added or asked for (a rollout of 16 games needs about a thousand),
    as sorted state codes (``_Deduplicator``'s) with the first moves of each (a bit mask)."""

    def __init__(self, config: GameConfig, capacity: int = 4096):
        n_agents = _mask_agents(config)
        self.config, self.capacity = config, capacity
        self._board = _board_of(config)
        # the smallest kept: tens of megabytes at capacity with 64-bit codes and masks on a 50x50 board
        n_codes = self._board.height * self._board.width * self._board.n_offsets ** (n_agents - 1)
        self._code_type = np.int32 if n_codes < 2 ** 31 else np.int64
        self._mask_type = np.uint16 if N_ACTIONS ** n_agents <= 16 else np.uint64
        self._tables: OrderedDict[tuple, list[tuple[np.ndarray, np.ndarray, int]]] = OrderedDict()

    def check(self, config: GameConfig) -> None:
        if config != self.config:
            raise ConfigError("ahead: it holds what searches of another game config found")

    def get(self, scenario: Scenario) -> tuple[int, int] | None:
        """``(length, first moves mask)`` of a known state, as ``_search_first_moves`` finds them; None if unknown."""
        tables = self._tables.get(scenario.obstacles)
        code = self._code(scenario) if tables else None
        if code is None:
            return None
        for codes, masks, length in tables:
            i = int(np.searchsorted(codes, code))
            if i < len(codes) and codes[i] == code:
                self._tables.move_to_end(scenario.obstacles)
                return length, int(masks[i])
        return None

    def add(self, layers: list[tuple[np.ndarray, np.ndarray, np.ndarray]], obstacles: list[list[tuple]],
            found: list[tuple[int, int | None] | None]) -> None:
        """Keep ``_shortest_ahead``'s ``layers`` of a search whose scenario k had ``obstacles[k][t - 1]`` after
        step t and a shortest path of length ``found[k][0]``."""
        for t, (codes, owner, masks) in enumerate(layers, start=1):
            order = np.lexsort((codes, owner))
            codes, owner = codes[order].astype(self._code_type), owner[order]
            masks = masks[order].astype(self._mask_type)
            ends = [*np.flatnonzero(np.diff(owner)) + 1, len(owner)]
            for begin, end in zip([0, *ends[:-1]], ends):
                if begin == end:
                    continue
                k = int(owner[begin])
                key = obstacles[k][t - 1]
                tables = self._tables.setdefault(key, [])
                tables.insert(0, (codes[begin:end], masks[begin:end], found[k][0] - t))
                del tables[4:]  # searched again from elsewhere: the newest few
                self._tables.move_to_end(key)
        while len(self._tables) > self.capacity:
            self._tables.popitem(last=False)

    def _code(self, scenario: Scenario) -> int | None:
        """The state code of the team (as ``_state_codes``), None for a follower beyond reach."""
        b, (row, col) = self._board, scenario.leader
        code = row * b.width + col
        for r, c in scenario.followers:
            if abs(r - row) > b.reach_rows or abs(c - col) > b.reach_cols:
                return None
            code = code * b.n_offsets + (r - row + b.reach_rows) * (2 * b.reach_cols + 1) + c - col + b.reach_cols
        return code


def _shortest_ahead(trace: list, n_starts: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per layer t >= 1 of a traced ``_search_first_moves``, the states on a shortest path of their scenario (one
    ending in its first layer with a success): their codes, scenarios and the first moves of those paths from
    them (bit masks). Marked from the last layer back: a state is on one when a move from it reaches a success
    or a state on one."""
    marks = np.zeros(len(trace[-1][5]), np.uint64)  # over the states of the layer after the one being marked
    ahead = []
    for t in range(len(trace) - 1, -1, -1):
        won_parent, won_joint, parent, joint, slot, codes, owner = trace[t]
        good = marks[slot] != 0
        parents = np.concatenate([won_parent, parent[good]])
        joints = np.concatenate([won_joint, joint[good]]).astype(np.uint64)
        on = np.flatnonzero(marks)
        ahead.append((codes[on], owner[on], marks[on]))
        marks = np.zeros(n_starts if t == 0 else len(trace[t - 1][5]), np.uint64)
        np.bitwise_or.at(marks, parents, np.uint64(1) << joints)
    ahead.reverse()
    return ahead


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


_BOARDS: dict[tuple, _Board] = {}


def _board_of(config: GameConfig) -> _Board:
    """The ``_Board`` of a config's board and formation limits, built once: its move tables cost more
    to build than a search of a few states."""
    key = (config.height, config.width, config.destination, config.d_min, config.d_max)
    if key not in _BOARDS:
        if len(_BOARDS) >= 8:
            _BOARDS.clear()
        _BOARDS[key] = _Board(config)
    return _BOARDS[key]


class _Board:
    """Lookup tables over the cells of the board; a cell is the integer ``row * W + col``."""

    def __init__(self, config: GameConfig):
        H, W = config.height, config.width
        self.height, self.width = H, W
        self.row, self.col = np.divmod(np.arange(H * W, dtype=np.int32), W)
        # next_cell[cell, action]: where an agent lands, clamped to the board (docs/GAME.md, 'Actions').
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
        self._moves: dict[int, _MoveTable] = {}
        self._scratch = threading.local()

    def marks(self, size: int) -> np.ndarray:
        """A scratch array of ``size`` indices for ``_Deduplicator``, up to ``KEPT_MARKS`` of them kept from one
        search to the next: a fresh one of millions of entries costs a page fault per few hundred states
        marked. Per thread, and read only where written in the same call, so what it held before never
        matters. Larger ones are made for the search (int32, half the memory) and let go after it."""
        if size > KEPT_MARKS:
            return np.empty(size, np.int32)
        marks = getattr(self._scratch, "marks", None)
        if marks is None or len(marks) < size:
            marks = self._scratch.marks = np.empty(size, np.intp)
        return marks[:size]

    def moves(self, n_agents: int) -> _MoveTable | None:
        """The ``_MoveTable`` of a team of ``n_agents``, or None where it would have more than
        ``MOVE_TABLE_LIMIT`` entries."""
        n_codes = self.height * self.width * self.n_offsets ** (n_agents - 1)
        if n_codes * N_ACTIONS ** n_agents > MOVE_TABLE_LIMIT:
            return None
        if n_agents not in self._moves:
            self._moves[n_agents] = _MoveTable(self, n_agents)
        return self._moves[n_agents]


class _ObstacleFuture:
    """The collision zones ``Z_1, Z_2, ...`` of some scenarios, computed by the game as needed."""

    def __init__(self, config: GameConfig, scenarios: list[Scenario], board: _Board):
        self.board = board
        self.game = BatchedGame(config, batch_size=len(scenarios))
        self.game.load(scenarios)
        self.obstacle_rows = self.game.obstacle_rows.copy()  # (scenarios, obstacles)
        # _zones[scenario, t, cell]: is the cell in Z_t (t = 0 stands for the reset and stays empty).
        self._zones = np.zeros((len(scenarios), 1, board.height * board.width), bool)
        self._after: list[tuple[list, list]] = []  # per step t >= 1: every scenario's obstacle columns, velocities

    def obstacles(self, k: int) -> list[tuple]:
        """Scenario ``k``'s obstacles after every step swept so far, from step 1 on, as ``Scenario.obstacles``."""
        rows = self.obstacle_rows[k].tolist()
        return [tuple(zip(rows, cols[k], velocities[k])) for cols, velocities in self._after]

    def zones(self, n_steps: int) -> np.ndarray:
        """``(scenarios, n_steps + 1, H * W)`` bool: the collision zone of every step up to ``n_steps``."""
        known = self._zones.shape[1] - 1
        if n_steps > known:
            self._zones = np.concatenate([self._zones, self._sweep(n_steps - known)], axis=1)
        return self._zones[:, : n_steps + 1]

    def _sweep(self, n_steps: int) -> np.ndarray:
        board, n_scenarios = self.board, len(self.obstacle_rows)
        zones = np.zeros((n_scenarios, n_steps, board.height * board.width), bool)
        if self.game.n_obstacles == 0:
            self._after += [([[]] * n_scenarios, [[]] * n_scenarios)] * n_steps
            return zones
        # reached[t, s, k, o]: the column of scenario k's obstacle o after sub-step s of step t (a
        # scenario whose obstacles are slower than the batch's fastest reaches the same cell twice)
        reached = []
        for _ in range(n_steps):
            reached.append([cols.copy() for cols in self.game.sweep_obstacles()])
            game = self.game
            self._after.append((game.obstacle_cols.tolist(), (game.obstacle_dirs * game.obstacle_speeds).tolist()))
        reached = np.array(reached, dtype=np.int32)
        if reached.size == 0:
            return zones
        rows = self.obstacle_rows[None, None, :, :, None] + COLLISION_OFFSETS[:, 0]
        cols = reached[..., None] + COLLISION_OFFSETS[:, 1]
        rows = np.broadcast_to(rows, cols.shape)
        step = np.broadcast_to(np.arange(n_steps)[:, None, None, None, None], cols.shape)
        scenario = np.broadcast_to(np.arange(n_scenarios)[None, None, :, None, None], cols.shape)
        on_board = (rows >= 0) & (rows < board.height) & (cols >= 0) & (cols < board.width)
        zones[scenario[on_board], step[on_board], rows[on_board] * board.width + cols[on_board]] = True
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


def _search_first_moves(board: _Board, zones: np.ndarray, starts: np.ndarray, deadlines: np.ndarray,
                        masks: bool = True, trace: list | None = None) -> list[tuple[int, int | None] | None]:
    """``_search`` of several scenarios at once (``zones[k]``, ``starts[k]`` and ``deadlines[k]``:
    scenario k's zones, its agents' cells and its deadline). With ``masks``, every state of a layer
    carries the set of the first joint actions of the paths reaching it (a bit mask), merged over
    duplicates. Per scenario ``(length, mask)`` of the first layer with a success, ``mask`` over all
    the successes in it (None without ``masks``), or None where no success comes within its deadline.
    ``trace``: a list to append every layer's moves to, for ``_shortest_ahead``."""
    n_scenarios = len(starts)
    n_cells = board.height * board.width
    layers = _Layers(board, starts)
    layer, owner = layers.start, np.arange(n_scenarios)  # the states of a layer and the scenario of each
    firsts = None  # per state of the layer: its first joint actions (None at the start)
    found: list[tuple[int, int | None] | None] = [None] * n_scenarios
    for t in range(int(deadlines.max())):
        parent, joint, states = layers.successors(layer, zones[:, t + 1].reshape(-1), deadlines[owner] - t - 1,
                                                 offset=owner * n_cells)
        owner = owner[parent]
        if not masks:
            carried = None
        elif firsts is not None:
            carried = firsts[parent]
        else:
            carried = np.uint64(1) << joint.astype(np.uint64)
        success = layers.arrived(states)
        won = parent[:0], joint[:0]
        if success.any():
            winners = owner[success]
            if masks:
                totals = np.zeros(n_scenarios, np.uint64)
                np.bitwise_or.at(totals, winners, carried[success])
            for k in np.unique(winners):
                found[k] = (t + 1, int(totals[k]) if masks else None)
            playing = ~np.isin(owner, winners)
            states, owner = states[playing], owner[playing]
            carried = None if carried is None else carried[playing]
            if trace is not None:
                won = parent[success], joint[success]
                parent, joint = parent[playing], joint[playing]
        if len(states) == 0:
            if trace is not None:
                trace.append((*won, parent, joint, parent[:0], layers.codes(states), owner))
            break
        keep, inverse = layers.groups(states, owner, inverse=masks)
        if masks:
            firsts = np.zeros(len(keep), np.uint64)
            np.bitwise_or.at(firsts, inverse, carried)
        layer, owner = states[keep], owner[keep]
        if trace is not None:
            trace.append((*won, parent, joint, inverse, layers.codes(layer), owner))
    return found


def _successors(board: _Board, layer: np.ndarray, zone: np.ndarray, steps_left: int | np.ndarray,
                offset: np.ndarray | None = None):
    """Every allowed move from ``layer``: the parent state's index, the joint action, and the
    cells the agents land on, ``(moves, agents)``. ``offset``: see ``_expand``."""
    n_agents = layer.shape[1]
    landing, allowed = _expand(board, layer, zone, steps_left, offset)
    parent, joint = np.divmod(np.flatnonzero(allowed), N_ACTIONS ** n_agents)
    actions = [(joint // N_ACTIONS ** (n_agents - 1 - i)) % N_ACTIONS for i in range(n_agents)]
    cells = np.stack([landing[parent, i, a] for i, a in enumerate(actions)], axis=1)
    return parent, joint, cells


def _expand(board: _Board, layer: np.ndarray, zone: np.ndarray, steps_left: int | np.ndarray,
            offset: np.ndarray | None = None):
    """Every joint action from every state of ``layer``: ``landing[state, agent, action]`` (the
    cell an agent lands on) and ``allowed[state, a_leader, a_follower, ...]`` (no collision,
    formation kept, and the leader can still reach the destination in ``steps_left`` steps, one
    number or one per state). ``offset``: per state, where its scenario's zone starts in ``zone``
    (several scenarios' zones laid end to end); None: one scenario."""
    n, n_agents = layer.shape
    landing, safe = _landing(board, layer, zone, steps_left, offset)

    def along(values: np.ndarray, agent: int) -> np.ndarray:
        return _along(values, agent, n_agents)

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


def _landing(board: _Board, cells: np.ndarray, zone: np.ndarray, steps_left: int | np.ndarray,
             offset: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``landing[state, agent, action]``, the cell an agent of a state with ``cells`` lands on, and
    ``safe[state, agent, action]``: outside the zone, and for the leader, still able to arrive in
    ``steps_left`` steps (see ``_expand``)."""
    landing = board.next_cell[cells]  # (n, agents, actions)
    safe = ~zone[landing if offset is None else landing + offset[:, None, None]]
    safe[:, 0] &= board.steps_to_go[landing[:, 0]] <= np.reshape(steps_left, (-1, 1))
    return landing, safe


def _along(values: np.ndarray, agent: int, n_agents: int) -> np.ndarray:
    """Put an agent's per-action values ``(n, actions)`` on its own axis of the joint-action grid."""
    shape = [len(values)] + [1] * n_agents
    shape[1 + agent] = N_ACTIONS
    return values.reshape(shape)


class _MoveTable:
    """Every joint action from every joint state, by state code (``_Deduplicator``'s): ``next[code, joint]``
    is the code of the state it leads to, or -1 where it breaks the formation (checked as ``_expand``
    checks it), and ``cells[code]`` the agents' cells. A layer kept as codes is stepped with lookups
    instead of computing every move's distances and the new states' codes."""

    def __init__(self, board: _Board, n_agents: int):
        self.board = board
        n_codes = board.height * board.width * board.n_offsets ** (n_agents - 1)
        side = 2 * board.reach_cols + 1
        rest, offsets = np.arange(n_codes), []
        for _ in range(n_agents - 1):  # the last follower's offset is the least significant digit
            rest, offset = np.divmod(rest, board.n_offsets)
            offsets.insert(0, offset)
        leader, on_board, cells = rest, np.ones(n_codes, bool), [rest]
        for offset in offsets:
            rows = board.row[leader] + offset // side - board.reach_rows
            cols = board.col[leader] + offset % side - board.reach_cols
            inside = (rows >= 0) & (rows < board.height) & (cols >= 0) & (cols < board.width)
            on_board &= inside
            cells.append(np.where(inside, rows * board.width + cols, 0))
        self.cells = np.stack(cells, axis=1).astype(np.int32)  # codes of no state (a follower off the board): 0s
        self.leader = self.cells[:, 0].copy()
        joints = np.arange(N_ACTIONS ** n_agents)
        moves = [(joints // N_ACTIONS ** (n_agents - 1 - i)) % N_ACTIONS for i in range(n_agents)]
        landing = np.stack([board.next_cell[self.cells[:, i]][:, moves[i]] for i in range(n_agents)],
                           axis=2)  # (codes, joints, agents)
        rows, cols = board.row[landing], board.col[landing]

        def squared(a: int, b: int) -> np.ndarray:
            return (rows[..., a] - rows[..., b]) ** 2 + (cols[..., a] - cols[..., b]) ** 2
        kept = np.broadcast_to(on_board[:, None], landing.shape[:2]).copy()
        for f in range(1, n_agents):
            kept &= board.kept_of[squared(0, f)]
        for i in range(1, n_agents):
            for j in range(i + 1, n_agents):
                kept &= board.apart_of[squared(i, j)]
        codes = _state_codes(board, landing.reshape(-1, n_agents)).reshape(kept.shape)
        self.next = np.where(kept, codes, -1).astype(np.int32)
        self.landing = board.next_cell[self.cells].reshape(n_codes, -1)  # (codes, agents * actions)
        self.steps_to_go = board.steps_to_go[self.landing[:, :N_ACTIONS]]  # the leader's, after each action
        self.shift = 2 * n_agents  # joint actions per state: 1 << shift

    def codes(self, cells: np.ndarray) -> np.ndarray | None:
        """The codes of states ``(states, agents)``; None if one has no code (a follower beyond reach)."""
        codes = _state_codes(self.board, cells)
        if ((codes < 0) | (codes >= len(self.cells))).any():
            return None
        return codes if (self.cells[codes] == cells).all() else None

    def successors(self, codes: np.ndarray, zone: np.ndarray, steps_left: int | np.ndarray,
                   offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_successors`` of the states ``codes``, the new states as codes, and whether a leader may have
        reached the destination (else none has)."""
        n, n_agents = len(codes), self.cells.shape[1]
        landing = self.landing[codes]
        safe = ~zone[landing if offset is None else landing + offset[:, None]]
        steps_to_go = self.steps_to_go[codes]
        arriving = bool(len(steps_to_go)) and steps_to_go.min() == 0
        safe[:, :N_ACTIONS] &= steps_to_go <= np.reshape(steps_left, (-1, 1))
        safe = safe.reshape(n, n_agents, N_ACTIONS)
        following = self.next[codes]  # (n, joints)
        allowed = following.reshape((n,) + (N_ACTIONS,) * n_agents) >= 0
        for agent in range(n_agents):
            allowed = allowed & _along(safe[:, agent], agent, n_agents)
        moves = np.flatnonzero(allowed)
        return moves >> self.shift, moves & ((1 << self.shift) - 1), following.reshape(-1)[moves], arriving


class _Layers:
    """Steps the layers of a search over several scenarios, one scenario's states after another's
    (``owner``): as codes through the board's ``_MoveTable``, or where it has none (or a start has no
    code), as cells ``(states, agents)`` through ``_successors``."""

    def __init__(self, board: _Board, starts: np.ndarray):
        n_scenarios, n_agents = starts.shape
        self.board, self.table = board, board.moves(n_agents)
        self.dedupe = _Deduplicator(board, n_agents, n_scenarios)
        self.start = starts if self.table is None else self.table.codes(starts)
        self._arriving = True
        if self.start is None:
            self.table, self.start = None, starts

    def successors(self, layer: np.ndarray, zone: np.ndarray, steps_left: int | np.ndarray, offset: np.ndarray):
        if self.table is None:
            return _successors(self.board, layer, zone, steps_left, offset)
        parent, joint, states, self._arriving = self.table.successors(layer, zone, steps_left, offset)
        return parent, joint, states

    def arrived(self, layer: np.ndarray) -> np.ndarray:
        """Whether the leader of each state of ``successors``' last answer stands on the destination."""
        if self.table is None:
            return layer[:, 0] == self.board.destination
        if not self._arriving:  # no leader came next to it: skip looking
            return np.zeros(len(layer), bool)
        return self.table.leader[layer] == self.board.destination

    def codes(self, layer: np.ndarray) -> np.ndarray:
        return _state_codes(self.board, layer) if self.table is None else layer

    def groups(self, layer: np.ndarray, owner: np.ndarray, inverse: bool = True
               ) -> tuple[np.ndarray, np.ndarray | None]:
        if self.table is None:
            return self.dedupe.groups(layer, owner, inverse)
        return self.dedupe.groups_of_codes(layer, owner, inverse)


class _Deduplicator:
    """Keeps one of each joint state in a layer. The code of a state is its leader's cell and
    each follower's offset from the leader (bounded, since every stored state keeps formation)."""

    def __init__(self, board: _Board, n_agents: int, n_scenarios: int = 1):
        self.board = board
        self.n_codes = board.height * board.width * board.n_offsets ** (n_agents - 1)  # per scenario
        total = self.n_codes * n_scenarios
        self.mark = board.marks(total) if total <= DENSE_CODES_LIMIT else None

    def __call__(self, cells: np.ndarray) -> np.ndarray:
        """Indices of the first (dense: some) copy of each distinct state among ``cells``."""
        codes = self._codes(cells)
        if self.mark is None:
            return np.sort(np.unique(codes, return_index=True)[1])
        order = np.arange(len(codes))
        self.mark[codes] = order
        return np.flatnonzero(self.mark[codes] == order)

    def groups(self, cells: np.ndarray, owner: np.ndarray, inverse: bool = True
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """States of several scenarios (``owner``: each one's scenario): the index of one copy of
        each distinct (scenario, state), and for every state the position of its copy in that list
        (None unless ``inverse``)."""
        return self.groups_of_codes(self._codes(cells), owner, inverse)

    def groups_of_codes(self, codes: np.ndarray, owner: np.ndarray, inverse: bool = True
                        ) -> tuple[np.ndarray, np.ndarray | None]:
        """``groups`` of states given by their codes."""
        codes = owner * self.n_codes + codes
        if self.mark is None:
            _, keep, positions = np.unique(codes, return_index=True, return_inverse=True)
            return keep, positions if inverse else None
        order = np.arange(len(codes))
        self.mark[codes] = order
        copy = self.mark[codes]  # the index of one copy of each state, the same for all its copies
        keep = np.flatnonzero(copy == order)
        if not inverse:
            return keep, None
        slot = np.empty(len(codes), np.intp)
        slot[keep] = np.arange(len(keep))
        return keep, slot[copy]

    def _codes(self, cells: np.ndarray) -> np.ndarray:
        return _state_codes(self.board, cells)


def _state_codes(b: _Board, cells: np.ndarray) -> np.ndarray:
    """The code of each state ``(states, agents)``: its leader's cell, then each follower's offset from it."""
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
