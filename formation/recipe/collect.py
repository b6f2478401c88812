"""Collecting: the team's networks play a batch of games epsilon-greedily, and every step becomes replay records.

``Collector`` is the acting half of the recipe, the same for every way of running it: the RLlib rollout actors
(``formation.rllib.rollout_actor``) wrap it, and so does the single-process loop (``formation.recipe.loop``). Each
``collect`` plays some steps of all its games with the networks it is given and returns their records (a
``Chunk``, for the replay) and the episodes that ended. With a teacher (the ``teacher`` section) the clairvoyant
planner labels every state the games visit, a share of the games play those labels, and with
``teacher.safety_horizon`` it also labels the joint moves that start safe steps. No Ray.
"""

from __future__ import annotations

import numpy as np
import torch

from formation.game import MOVES
from formation.recipe.config import RunConfig, TrainSettings
from formation.recipe.qnet import q_values_of, team_q_values
from formation.recipe.replay import Chunk
from formation.recipe.rollout import GameRollout, concatenate
from formation.recipe.shaping import Potential
from formation.recipe.stopwatch import Stopwatch
from formation.recipe.teacher import Teacher, safety_labels
from formation.recipe.team import module_of_agent, reads_cells


def epsilon_at(env_steps: int, train: TrainSettings) -> float:
    """Exploration rate after ``env_steps``: linear from epsilon_start to epsilon_end over epsilon_env_steps."""
    done = min(1.0, env_steps / train.epsilon_env_steps)
    return train.epsilon_start + done * (train.epsilon_end - train.epsilon_start)


def epsilon_greedy(greedy: np.ndarray, epsilon: float, rng: np.random.Generator, joint: bool,
                   n_actions: int = 4) -> np.ndarray:
    """Epsilon-greedy actions from the greedy ones, both (games, agents), leader first.

    Independent: every agent explores on its own with probability ``epsilon``. Joint: a game's team
    explores with probability ``epsilon`` and then every agent takes the leader's random move, so
    exploring does not break the formation at once."""
    games, agents = greedy.shape
    if joint:
        explore = np.repeat(rng.random((games, 1)) < epsilon, agents, axis=1)
        random = np.repeat(rng.integers(0, n_actions, (games, 1)), agents, axis=1)
    else:
        explore = rng.random((games, agents)) < epsilon
        random = rng.integers(0, n_actions, (games, agents))
    return np.where(explore, random, greedy).astype(greedy.dtype)


class Collector:
    def __init__(self, run: RunConfig, index: int = 0):
        """The games of rollout actor ``index`` (each actor's games and exploration draw from streams of their own)."""
        t, games = run.train, run.resources.games_per_actor
        self.run = run
        self.modules = module_of_agent(run)
        self.rollout = GameRollout(run.game, games, seed=t.seed * 10_007 + index, stream_offset=index * games,
                                   potential=Potential(run.game) if t.shaping > 0 else None, shaping=t.shaping,
                                   gamma=t.gamma, exploring_starts=t.exploring_starts, screen_cells=reads_cells(run),
                                   reward_formation_kept=t.reward_formation_kept, team_reward=t.team_reward)
        self.rng = np.random.default_rng([t.seed, index])  # exploration
        self.teacher = Teacher.of_run(run) if run.teacher is not None else None
        self.demo_games = int(round(run.teacher.demonstrations * games)) if run.teacher is not None else 0
        self.clock = Stopwatch()  # seconds per stage

    def collect(self, networks: dict[str, torch.nn.Module], steps: int, env_steps: int) -> tuple[Chunk, list[dict]]:
        """Play ``steps`` steps of every game with ``networks`` (module -> Q-network), exploring at the rate of
        ``env_steps`` env steps into training; the records of those steps, and the episodes that ended."""
        clock, chunks = self.clock, []
        for _ in range(steps):
            with clock("act"):
                actions = self.actions(networks, env_steps)
            labels = answers = safe = None
            if self.teacher is not None:
                with clock("teacher"):
                    joints = self._teacher_joints()
                    # demonstration games play the teacher's labels where it has one
                    demo = slice(0, self.demo_games)
                    actions[demo] = np.where(joints[demo] >= 0, joints[demo], actions[demo])
                    labels, answers = self._labels(joints, actions)
                if self.run.safety_head:
                    with clock("safety"):
                        game = self.rollout.game
                        safe = safety_labels([game.scenario(i) for i in range(game.batch_size)], game.config,
                                             self.run.teacher.safety_horizon)
            with clock("game"):
                chunks.append(self.rollout.step(actions, labels=labels, answers=answers, safe=safe))
        return concatenate(chunks), self.rollout.pop_episodes()

    def actions(self, networks: dict[str, torch.nn.Module], env_steps: int) -> np.ndarray:
        """The epsilon-greedy actions (games, agents) to play. Followers that answer the leader
        (``train.follower_answers_leader``) answer the move the leader plays, and explore on their own only
        with ``train.exploration: independent``."""
        t, modules = self.run.train, self.modules
        with torch.no_grad():
            q = q_values_of(networks, torch.from_numpy(self.rollout.observations))
        q = {m: v.numpy() for m, v in q.items()}
        greedy = team_q_values(q, modules).argmax(-1)
        epsilon = epsilon_at(env_steps, t)
        if not t.follower_answers_leader:
            return epsilon_greedy(greedy, epsilon, self.rng, joint=t.exploration == "joint")
        leader = epsilon_greedy(greedy[:, :1], epsilon, self.rng, joint=False)[:, 0]
        actions = team_q_values(q, modules, leader_moves=leader).argmax(-1)
        actions[:, 0] = leader  # its own column holds its greedy move
        if t.exploration == "independent":
            actions[:, 1:] = epsilon_greedy(actions[:, 1:], epsilon, self.rng, joint=False)
        return actions

    # -- the teacher's labels
    def _teacher_joints(self) -> np.ndarray:
        """DAgger: the teacher's joint action in every game's present state, -1 where it has none."""
        game, joints = self.rollout.game, np.full((self.rollout.batch_size, self.rollout.n_agents), -1, np.int8)
        scenarios = [game.scenario(i) for i in range(self.rollout.batch_size)]
        for i, joint in enumerate(self.teacher.labels(scenarios, list(game.steps == 0))):
            if joint is not None:
                joints[i] = joint
        return joints

    def _labels(self, joints: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The labels to learn from, and the answers (``Chunk``) or None: the teacher's ``joints``; with
        ``train.follower_answers_leader`` the teacher's answer to the move the leader plays (``actions``), -1
        for the followers where no move of theirs survives it; with ``teacher.answer_every_leader_move`` also
        its answers to every move the leader could have made."""
        game = self.rollout.game
        if not self.run.train.follower_answers_leader:
            return joints, None
        labels = joints.copy()
        leader = actions[:, 0]
        if self.run.teacher.answer_every_leader_move:
            answers = np.full((*joints.shape, len(MOVES)), -1, np.int8)
            for i in np.flatnonzero(joints[:, 0] >= 0):
                scenario, joint = game.scenario(i), tuple(int(a) for a in joints[i])
                for move, answer in enumerate(self.teacher.answers(scenario, joint)):
                    if answer is not None:
                        answers[i, 1:, move] = answer[1:]
                labels[i, 1:] = answers[i, 1:, leader[i]]
            return labels, answers
        # where the leader makes the teacher's move, the label stands as it is
        for i in np.flatnonzero((joints[:, 0] >= 0) & (leader != joints[:, 0])):
            answer = self.teacher.answer(game.scenario(i), tuple(int(a) for a in joints[i]), int(leader[i]))
            labels[i, 1:] = answer[1:] if answer is not None else -1
        return labels, None
