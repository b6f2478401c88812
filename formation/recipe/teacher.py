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

from formation.config import GameConfig
from formation.game import MOVES, BatchedGame, Scenario
from formation.planner import (
    FirstMovesAhead,
    lower_bound,
    paths_exist,
    shortest_first_moves_many,
    shortest_path,
    surviving_first_moves_many,
)

# robust first-step labels try every velocity of this many obstacles, those nearest the leader's row;
# the others count as known (4 velocities each: trying all 3 of setting 1 costs 64 planner calls a label)
ROBUST_OBSTACLES = 2


def lockstep_order(n_agents: int, toward: int) -> list[tuple[int, ...]]:
    """Every joint action, lockstep ones (all agents the same move) first, then by each agent's move,
    leader first: forward, sideways ``toward`` the destination (1 = FL or 2 = FR), the other way, stay."""
    rank = {0: 0, toward: 1, 3 - toward: 2, 3: 3}
    return sorted(itertools.product(range(4), repeat=n_agents), key=lambda a: (len(set(a)) > 1, [rank[m] for m in a]))


class Teacher:
    """DAgger labels from the clairvoyant planner: a joint action for a game's present state.

    Of the joint actions that start a shortest path (often 8 of the 16), the label is the first in
    ``lockstep_order``, so that labels follow one simple rule. ``robust_first_step``: on an episode's first
    step, whose screens do not show the obstacles' motion yet, the first joint action in ``lockstep_order``
    after which a path is left for the most velocities of the obstacles nearest the agents, instead of the
    clairvoyant one. Paths count up to the lower bound + ``slack`` steps; a state with none gets no label
    (None).
    """

    def __init__(self, config: GameConfig, slack: int, robust_first_step: bool = False):
        self.config, self.slack, self.robust_first_step = config, slack, robust_first_step
        self._probe = BatchedGame(config, batch_size=1)  # plays one joint action from a scenario
        self._capped: dict[int, GameConfig] = {}
        self._robust_labels: dict[tuple, tuple[int, ...] | None] = {}
        self._found: dict[Scenario, set[tuple[int, ...]] | None] = {}  # _starts, oldest first
        self._unsearched: list[Scenario] = []  # the robust first steps of the last labels()
        self._labelled: list[Scenario] = []  # the states of the last labels()
        # _survives' joint actions (bit masks) from the planner's first step, as the game plays it, where no
        # truncation can differ: no step limit at the first step, nor one below the leader's farthest way
        self._surviving: dict[Scenario, int] | None = None
        if config.n_followers <= 2 and config.max_steps >= max(config.height, config.width):
            self._surviving = {}
        # the states on the shortest paths found: a rollout's next states are mostly among them
        self._ahead = FirstMovesAhead(config) if config.n_followers <= 2 else None
        destination, agents = config.destination[1], 1 + config.n_followers
        self._orders = [lockstep_order(agents, 2 if col < destination else 1) for col in range(config.width)]
        speeds = [sign * speed for speed in config.obstacle_speeds for sign in (1, -1)]
        self._velocities = list(itertools.product(speeds, repeat=min(ROBUST_OBSTACLES, config.n_obstacles)))
        self._hypotheses = BatchedGame(config, batch_size=len(self._velocities))  # one game per velocity

    @classmethod
    def of_run(cls, run) -> Teacher:
        """The teacher of a training config (``RunConfig``): its game and ``teacher`` section."""
        return cls(run.game, run.teacher.planner_slack, run.teacher.robust_first_step)

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
        (``teacher.answer_every_leader_move``)."""
        return [self.answer(scenario, joint, move) for move in range(len(MOVES))]

    def _shortest_with(self, scenario: Scenario, leader_move: int) -> tuple[int, ...] | None:
        """The first joint action in the order with ``leader_move`` that starts a shortest path; None if none does."""
        starts = self._starts(scenario) or set()
        return next((j for j in self._order(scenario) if j[0] == leader_move and j in starts), None)

    def _starts(self, scenario: Scenario) -> set[tuple[int, ...]] | None:
        """The joint actions that start a shortest path within the slack (None: no path), from one
        search; the last few are kept, since a state's label and its answers need the same."""
        self._find_starts(self._unsearched if scenario in self._unsearched else [scenario])
        return self._found[scenario]

    def _find_starts(self, scenarios: list[Scenario]) -> None:
        """``_starts`` of every scenario not yet kept, from one batched search."""
        missing = list(dict.fromkeys(s for s in scenarios if s not in self._found))
        if not missing:
            return
        found = shortest_first_moves_many(missing, config=self.config, max_steps=[self._limit(s) for s in missing],
                                          ahead=self._ahead)
        asked = set(scenarios)  # never dropped for each other: the caller reads them next
        for scenario, starts in zip(missing, found):
            oldest = next((s for s in self._found if s not in asked), None) if len(self._found) >= 256 else None
            if oldest is not None:
                self._found.pop(oldest)
            self._found[scenario] = set(starts[1]) if starts is not None else None

    def _survives(self, scenario: Scenario, joint: tuple[int, ...]) -> bool:
        """Whether the team is still playing, or has won, after ``joint``."""
        if self._surviving is not None:
            if scenario not in self._surviving:  # found for the whole last labels() batch at once
                batch = self._labelled if scenario in self._labelled else [scenario]
                if len(self._surviving) > 1024:
                    self._surviving.clear()
                masks = surviving_first_moves_many(batch, config=self.config, horizon=1)
                self._surviving.update(zip(batch, masks.tolist()))
            return bool(self._surviving[scenario] >> _joint_index(joint) & 1)
        probe = self._probe
        probe.load([scenario])
        probe.step(np.array([joint]))
        return bool(probe.success[0] or not probe.done[0])

    def _order(self, scenario: Scenario) -> list[tuple[int, ...]]:
        return self._orders[scenario.leader[1]]

    def labels(self, scenarios: list[Scenario], first_steps: list[bool]) -> list[tuple[int, ...] | None]:
        """``label`` of every scenario (``first_steps[i]``: whether it is an episode's first step),
        with the shortest-path searches of the lot run at once."""
        if self.config.n_followers <= 2:
            robust = [first and self.robust_first_step for first in first_steps]
            self._find_starts([s for s, r in zip(scenarios, robust) if not r])
            # answers to other leader moves than the robust label's need them: all searched at once when first asked
            self._unsearched = [s for s, r in zip(scenarios, robust) if r]
        self._labelled = list(scenarios)
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
        if self.config.n_followers <= 2:  # one search finds every first move
            starts = self._starts(scenario)
            if starts is None:
                return None
            return next(joint for joint in order if joint in starts)
        path = self._path(scenario)
        if path is None:
            return None
        planned = tuple(int(a) for a in path[0])
        for joint in order:
            if joint == planned or self._opens(scenario, joint, max_steps=len(path) - 1):
                return joint
        return planned

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


def _joint_index(joint: tuple[int, ...]) -> int:
    """A joint action's bit in the planner's masks: the leader's move the most significant base-4 digit."""
    index = 0
    for move in joint:
        index = index * len(MOVES) + move
    return index


def safety_labels(scenarios: list[Scenario], config: GameConfig, horizon: int) -> np.ndarray:
    """What a safety head learns (``teacher.safety_horizon``) of states ``scenarios``, as ``(scenarios,)`` bit
    masks of joint actions (the planner on the true state): those that start ``horizon`` steps free of
    collisions and formation breaks."""
    return surviving_first_moves_many(scenarios, config=config, horizon=horizon)
