"""DAgger's teacher: the clairvoyant planner's joint action for any state a learner visits.

The planner knows the obstacles' velocities; the learners see them only from the second screen on.
Labels are made learnable in two ways: among the joint actions that start a shortest path, a fixed
order picks one (``lockstep``), and on an episode's first step the label is the joint action that
keeps a path open for the most obstacle velocities (``robust_first_step``), so the same first
screen always gets the same label.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from formation.config import GameConfig, formation_broken_by
from formation.game import MOVES, BatchedGame, Scenario
from formation.game.core import joint_mask
from formation.learn.config import SAFETY_PATH
from formation.planner import (
    lower_bound,
    paths_exist,
    shortest_first_moves_many,
    shortest_path,
    shortest_path_counts,
    surviving_first_moves_many,
    viable_first_moves_many,
)

# robust first-step labels try every velocity of this many obstacles, those nearest the leader's row;
# the others count as known (4 velocities each: trying all 3 of setting 1 costs 64 planner calls a label)
ROBUST_OBSTACLES = 2
SLIPS = ((-1, 0), (1, 0), (0, -1), (0, 1))  # tolerant_formation: one cell off where an agent lands
SHORTEST_PATH_ORDERS = ("lockstep", "toward")  # orders that label with a move starting a shortest path


def lockstep_order(n_agents: int, toward: int, toward_first: bool = False) -> list[tuple[int, ...]]:
    """Every joint action, lockstep ones (all agents the same move) first, then by each agent's move,
    leader first: forward, sideways ``toward`` the destination (1 = FL or 2 = FR), the other way, stay;
    with ``toward_first``, the sideways move towards the destination before forward."""
    rank = {toward: 0, 0: 1, 3 - toward: 2, 3: 3} if toward_first else {0: 0, toward: 1, 3 - toward: 2, 3: 3}
    return sorted(itertools.product(range(4), repeat=n_agents), key=lambda a: (len(set(a)) > 1, [rank[m] for m in a]))


class Teacher:
    """DAgger labels from the clairvoyant planner: a joint action for a game's present state.

    ``order="planner"``: the first action of the planner's shortest path. ``order="lockstep"``: of the
    joint actions that start a shortest path (often 8 of the 16), the first in ``lockstep_order``, so
    that labels follow one simple rule; ``order="toward"``: the same with the sideways move towards the
    destination's column ranked before forward. ``order="safe"``: the first joint action in
    ``lockstep_order``, those that bring the leader closer first, after which a path is left (forward unless that dooms
    the team), a rule that depends mostly on the obstacles nearby. ``order="widest"``: of the lockstep joint
    actions that start a shortest path (of all, if none does), the one that starts the most shortest
    paths (ties by ``lockstep_order``), so that the team keeps to states where many moves still lead
    along a shortest path. ``tolerant_formation``: the joint actions after which the formation would survive
    any one agent landing a cell off (up, down, left or right) come first in the order. ``robust_first_step``:
    on an episode's first step, whose screens do not show the obstacles' motion yet, the first joint
    action in ``lockstep_order`` after which a path is left for the most velocities of the
    obstacles nearest the agents, instead of the clairvoyant one.
    Paths count up to the lower bound + ``slack`` steps; a state with none gets no label (None).
    """

    def __init__(self, config: GameConfig, slack: int, order: str = "planner", robust_first_step: bool = False,
                 tolerant_formation: bool = False):
        self.config, self.slack, self.order, self.robust_first_step = config, slack, order, robust_first_step
        self.tolerant_formation = tolerant_formation
        self._probe = BatchedGame(config, batch_size=1)  # plays one joint action from a scenario
        self._capped: dict[int, GameConfig] = {}
        self._robust_labels: dict[tuple, tuple[int, ...] | None] = {}
        self._found: dict[Scenario, set[tuple[int, ...]] | None] = {}  # _starts, oldest first
        destination, agents = config.destination[1], 1 + config.n_followers
        # "toward": the team heads for the destination's column first (below the obstacles), then forward
        self._orders = [lockstep_order(agents, 2 if col < destination else 1, order == "toward" and col != destination)
                        for col in range(config.width)]
        speeds = [sign * speed for speed in config.obstacle_speeds for sign in (1, -1)]
        self._velocities = list(itertools.product(speeds, repeat=min(ROBUST_OBSTACLES, config.n_obstacles)))
        self._hypotheses = BatchedGame(config, batch_size=len(self._velocities))  # one game per velocity

    @classmethod
    def of_run(cls, run) -> Teacher:
        """The teacher of a training config (``RunConfig``): its game and ``train`` labelling settings."""
        t = run.train
        return cls(run.game, t.planner_slack, t.label_order, t.robust_first_step, t.tolerant_formation)

    def respond(self, scenario: Scenario, joint: tuple[int, ...], leader_move: int, first_step: bool = False
                ) -> tuple[int, ...]:
        """``joint`` (the state's label) with the followers' part answering ``leader_move``, the move the
        leader's own network makes: the followers' moves of the first joint action in the order that starts
        a shortest path with the leader making that move, where one does and the order is ``lockstep`` or
        ``toward``; otherwise, and on a first step with ``robust_first_step``, ``joint`` as it is. The
        leader's part stays the teacher's."""
        if leader_move == joint[0] or self.order not in SHORTEST_PATH_ORDERS or self.config.n_followers > 2 \
                or (first_step and self.robust_first_step):
            return joint
        answer = self._shortest_with(scenario, leader_move)
        return joint if answer is None else (joint[0], *answer[1:])

    def answer(self, scenario: Scenario, joint: tuple[int, ...], leader_move: int) -> tuple[int, ...] | None:
        """The joint action to learn when the leader makes ``leader_move`` (``train.follower_answers_leader``):
        ``joint``, the state's label, where the leader makes its move; else, of the joint actions with
        that leader move in the order, the first that starts a shortest path, or failing that the first
        after which nobody collides and the formation holds; None where every one ends the episode.
        On a first step ``joint`` may be the robust label, the one that keeps a path for the most
        velocities of the obstacles; the answers to other leader moves are the clairvoyant ones."""
        if leader_move == joint[0]:
            return joint
        shortest = self._shortest_with(scenario, leader_move) if self.config.n_followers <= 2 else None
        surviving = (j for j in self._order(scenario) if j[0] == leader_move and self._survives(scenario, j))
        return shortest or next(surviving, None)

    def answers(self, scenario: Scenario, joint: tuple[int, ...]) -> list[tuple[int, ...] | None]:
        """``answer`` to each move the leader could make, in the order of the moves
        (``train.answer_every_leader_move``)."""
        return [self.answer(scenario, joint, move) for move in range(len(MOVES))]

    def accepted(self, scenario: Scenario, joint: tuple[int, ...], first_step: bool = False,
                 toward: bool = False) -> int:
        """The joint actions a learner may take for ``joint``, the state's label (``train.any_shortest_move``),
        as a bit mask: bit ``4 * leader's move + follower's move`` (one follower) of every joint action that
        starts a shortest path; only the label's on a first step with ``robust_first_step``, and where the
        order does not label with a shortest path's start. ``toward``: besides the label, only those whose
        leader move does not take the leader farther from the destination's column."""
        if self.config.n_followers != 1:
            raise ValueError(f"Teacher.accepted: one follower only, not {self.config.n_followers}")
        starts = set()
        if self.order in SHORTEST_PATH_ORDERS and not (first_step and self.robust_first_step):
            starts = self._starts(scenario) or set()
        if toward:
            column, now = self.config.destination[1], scenario.leader[1]
            starts = {j for j in starts if abs(self._landing(scenario.leader, j[0])[1] - column) <= abs(now - column)}
        return joint_mask(starts | {joint})

    def shortest_starts(self, scenarios: list[Scenario]) -> np.ndarray:
        """The joint actions that start a shortest path within the slack, as ``(scenarios,)`` bit masks (0 where
        no path is left; one follower), from the searches ``labels`` ran on the same states where it did."""
        if self.config.n_followers != 1:
            raise ValueError(f"Teacher.shortest_starts: one follower only, not {self.config.n_followers}")
        self._find_starts(scenarios)
        return np.array([joint_mask(self._starts(s) or ()) for s in scenarios], np.uint64)

    def _shortest_with(self, scenario: Scenario, leader_move: int) -> tuple[int, ...] | None:
        """The first joint action in the order with ``leader_move`` that starts a shortest path; None if none does."""
        starts = self._starts(scenario) or set()
        return next((j for j in self._order(scenario) if j[0] == leader_move and j in starts), None)

    def _starts(self, scenario: Scenario) -> set[tuple[int, ...]] | None:
        """The joint actions that start a shortest path within the slack (None: no path), from one
        search; the last few are kept, since a state's label and its answers need the same."""
        self._find_starts([scenario])
        return self._found[scenario]

    def _find_starts(self, scenarios: list[Scenario]) -> None:
        """``_starts`` of every scenario not yet kept, from one batched search."""
        missing = list(dict.fromkeys(s for s in scenarios if s not in self._found))
        if not missing:
            return
        found = shortest_first_moves_many(missing, config=self.config, max_steps=[self._limit(s) for s in missing])
        for scenario, starts in zip(missing, found):
            if len(self._found) >= 256:
                self._found.pop(next(iter(self._found)))
            self._found[scenario] = set(starts[1]) if starts is not None else None

    def _survives(self, scenario: Scenario, joint: tuple[int, ...]) -> bool:
        """Whether the team is still playing, or has won, after ``joint``."""
        probe = self._probe
        probe.load([scenario])
        probe.step(np.array([joint]))
        return bool(probe.success[0] or not probe.done[0])

    def _order(self, scenario: Scenario) -> list[tuple[int, ...]]:
        order = self._orders[scenario.leader[1]]
        if self.tolerant_formation:  # first the joint actions after which one agent's slip cannot break the formation
            order = sorted(order, key=lambda joint: not self._tolerant(scenario, joint))
        return order

    def labels(self, scenarios: list[Scenario], first_steps: list[bool]) -> list[tuple[int, ...] | None]:
        """``label`` of every scenario (``first_steps[i]``: whether it is an episode's first step),
        with the shortest-path searches of the lot run at once."""
        if self.order in SHORTEST_PATH_ORDERS and self.config.n_followers <= 2:
            self._find_starts([s for s, first in zip(scenarios, first_steps) if not (first and self.robust_first_step)])
        return [self.label(s, first) for s, first in zip(scenarios, first_steps)]

    def label(self, scenario: Scenario, first_step: bool = False) -> tuple[int, ...] | None:
        """The joint action that labels ``scenario``; None where no path is left within the slack."""
        order = self._order(scenario)
        if first_step and self.robust_first_step:
            near = self._nearest_obstacles(scenario)
            seen = (scenario.leader, scenario.followers,
                    tuple((r, c, None if i in near else v) for i, (r, c, v) in enumerate(scenario.obstacles)))
            if seen not in self._robust_labels:  # few distinct first screens on a small board
                if len(self._robust_labels) > 100_000:
                    self._robust_labels.clear()
                self._robust_labels[seen] = self._robust(scenario, near, order)
            return self._robust_labels[seen]
        if self.order == "safe":  # the first move that keeps a path, those bringing the leader closer first
            for k, joint in enumerate(self._closer_first(scenario.leader, order)):
                if self._opens(scenario, joint):
                    return joint
                if k == 0 and self._path(scenario) is None:  # no path at all: nothing else will open one
                    return None
            return None
        if self.order == "widest":  # the start of the most shortest paths, lockstep if one starts any
            found = shortest_path_counts(scenario, config=self._capped_config(self._limit(scenario)))
            if found is None:
                return None
            counts = found[1]
            lockstep = [joint for joint in order if len(set(joint)) == 1 and joint in counts]
            return max(lockstep or order, key=lambda joint: counts.get(joint, 0.0))  # equal counts: by the order
        if self.order in SHORTEST_PATH_ORDERS and self.config.n_followers <= 2:  # one search finds every first move
            starts = self._starts(scenario)
            if starts is None:
                return None
            return next(joint for joint in order if joint in starts)
        path = self._path(scenario)
        if path is None:
            return None
        planned = tuple(int(a) for a in path[0])
        if self.order in SHORTEST_PATH_ORDERS:
            for joint in order:
                if joint == planned or self._opens(scenario, joint, max_steps=len(path) - 1):
                    return joint
        return planned

    def _closer_first(self, leader: tuple[int, int], order: list[tuple[int, ...]]) -> list[tuple[int, ...]]:
        """``order`` with the joint actions that lower the leader's steps to go first (stable)."""
        (row, col), (dest_row, dest_col) = leader, self.config.destination

        def to_go(move: int) -> int:
            r, c = self._landing(leader, move)
            return max(r - dest_row, abs(c - dest_col))

        now = max(row - dest_row, abs(col - dest_col))
        return sorted(order, key=lambda joint: to_go(joint[0]) >= now)

    def _landing(self, cell: tuple[int, int], move: int) -> tuple[int, int]:
        """The cell an agent at ``cell`` lands on with ``move`` (clamped to the board, spec rule 1)."""
        row = min(max(cell[0] + int(MOVES[move, 0]), 0), self.config.height - 1)
        return row, min(max(cell[1] + int(MOVES[move, 1]), 0), self.config.width - 1)

    def _tolerant(self, scenario: Scenario, joint: tuple[int, ...]) -> bool:
        """Whether, after ``joint``, the formation would still be kept with any one agent one cell up,
        down, left or right of where it lands: the slips a learner makes most (forward for a
        sideways move, or for a stay) then cannot break it on their own."""
        landed = [self._landing(cell, move) for cell, move in zip([scenario.leader, *scenario.followers], joint)]
        if formation_broken_by(self.config, landed[0], landed[1:]):
            return False
        for agent, (row, col) in enumerate(landed):
            for d_row, d_col in SLIPS:
                slipped = list(landed)
                slipped[agent] = (row + d_row, col + d_col)
                if formation_broken_by(self.config, slipped[0], slipped[1:]):
                    return False
        return True

    def _nearest_obstacles(self, scenario: Scenario) -> list[int]:
        """Indices of the ``ROBUST_OBSTACLES`` obstacles whose rows are nearest the leader's."""
        rows = [abs(r - scenario.leader[0]) for r, _, _ in scenario.obstacles]
        return sorted(range(len(rows)), key=lambda i: (rows[i], i))[:ROBUST_OBSTACLES]

    def _robust(self, scenario: Scenario, near: list[int], order: list[tuple[int, ...]]) -> tuple[int, ...] | None:
        """The first joint action in ``order`` that keeps a path open (``_opens``) for the most
        velocities of the ``near`` obstacles, every hypothesis played and searched at once."""
        hypotheses = []
        for velocities in self._velocities:
            obstacles = list(scenario.obstacles)
            for i, v in zip(near, velocities):
                obstacles[i] = (obstacles[i][0], obstacles[i][1], v)
            hypotheses.append(dataclasses.replace(scenario, obstacles=tuple(obstacles)))
        games = self._hypotheses
        best, best_count = None, 0
        for joint in order:
            games.load(hypotheses)
            games.step(np.tile(np.array(joint), (len(hypotheses), 1)))
            playing = [games.scenario(i) for i in np.flatnonzero(~games.done)]
            count = int(games.success.sum())
            if playing:
                limits = [self._limit(s) for s in playing]
                count += int(paths_exist(playing, config=self.config, max_steps=limits).sum())
            if count > best_count:
                best, best_count = joint, count
            if count == len(hypotheses):
                break
        return best

    def _opens(self, scenario: Scenario, joint: tuple[int, ...], max_steps: int | None = None) -> bool:
        """Whether ``joint`` wins at once or leaves a path of at most ``max_steps`` more steps
        (default: the lower bound + slack)."""
        probe = self._probe
        probe.load([scenario])
        probe.step(np.array([joint]))
        if probe.done[0] or max_steps == 0:
            return bool(probe.success[0])
        return self._path(probe.scenario(0), max_steps) is not None

    def _path(self, scenario: Scenario, max_steps: int | None = None) -> list | None:
        limit = max_steps if max_steps is not None else self._limit(scenario)
        return shortest_path(scenario, config=self._capped_config(limit))

    def _limit(self, scenario: Scenario) -> int:
        return lower_bound(scenario, self.config) + self.slack

    def _capped_config(self, max_steps: int) -> GameConfig:
        if max_steps not in self._capped:
            self._capped[max_steps] = self.config.replace(max_steps=max_steps)
        return self._capped[max_steps]


def safety_labels(scenarios: list[Scenario], steps: np.ndarray, config: GameConfig, horizon: int | str, slack: int,
                  planner_slack: int, teacher: Teacher | None = None) -> np.ndarray:
    """What a safety head learns (``train.safety_horizon``) of states ``scenarios``, ``steps[i]`` steps into
    their episodes, as ``(scenarios,)`` bit masks of joint actions (the planner on the true state): those
    that start ``horizon`` steps free of collisions and formation breaks; with ``horizon`` "path", those that
    start a successful path at most ``slack`` steps longer than a shortest one, within the teacher's deadline
    (the lower bound + ``planner_slack`` steps, and the episode's steps left). With slack 0, ``teacher`` (of
    the same ``planner_slack``), where given, answers from the searches its labels ran."""
    if horizon != SAFETY_PATH:
        return surviving_first_moves_many(scenarios, config=config, horizon=horizon)
    limits = np.array([lower_bound(s, config) + planner_slack for s in scenarios], np.int64)
    capped = np.minimum(limits, config.max_steps - np.asarray(steps))
    if slack == 0 and teacher is not None and (capped == limits).all():
        return teacher.shortest_starts(scenarios)
    return viable_first_moves_many(scenarios, config=config, slack=slack, max_steps=capped)
