"""Rollout actors: RLlib EnvRunners that play a batch of games and push records to the replay.

Each ``sample()`` plays ``steps_per_sample`` steps of all its games with the weights it was last
sent (epsilon-greedy, per agent or per team: ``train.exploration``), pushes the records straight to
its replay shard and returns only counts and finished-episode statistics, never transitions. It acts
on whole screens; where the networks read them per cell, the records it pushes hold only the cells
(``formation.recipe.rollout.GameRollout``), the replay's frames (``replay_frame_shape``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import ray
import torch
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.env import INPUT_ENV_SINGLE_SPACES, INPUT_ENV_SPACES
from ray.rllib.env.env_runner import EnvRunner
from ray.rllib.utils.checkpoints import Checkpointable
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME, WEIGHTS_SEQ_NO

from formation.game import MOVES
from formation.recipe.config import TrainSettings
from formation.recipe.qnet import q_values_of, team_q_values
from formation.recipe.rollout import GameRollout, concatenate
from formation.recipe.shaping import Potential
from formation.recipe.stopwatch import Stopwatch
from formation.recipe.teacher import Teacher, safety_labels
from formation.recipe.team import module_of_agent, reads_cells, spaces_of


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


class RolloutActor(EnvRunner, Checkpointable):
    def __init__(self, *, config, **kwargs):
        super().__init__(config=config, **kwargs)
        torch.set_num_threads(1)
        self.run = self.config.run  # the run config, the RLlib fields that name its keys merged in
        self._modules_of_agent = module_of_agent(self.run)
        self._weights_seq_no = 0
        self._replay = None
        self.num_env_steps_sampled_lifetime = 0
        self.clock = Stopwatch()  # seconds per stage, returned with every sample()
        self.make_env()
        self.make_module()

    # -- RLlib's EnvRunner API
    def make_env(self) -> None:
        run = self.run
        index = getattr(self, "worker_index", 0) or 0
        games = run.resources.games_per_actor
        t = run.train
        potential = Potential(t.potential, run.game) if t.shaping > 0 and t.potential != "none" else None
        self.rollout = GameRollout(run.game, games, seed=t.seed * 10_007 + index, stream_offset=index * games,
                                   potential=potential, shaping=t.shaping, gamma=t.gamma,
                                   exploring_starts=t.exploring_starts, screen_cells=reads_cells(run),
                                   reward_formation_kept=t.reward_formation_kept, team_reward=t.team_reward)
        self._rng = np.random.default_rng([t.seed, index])  # exploration
        self._demo_games = int(round(run.train.demonstrations * games))
        self._plans: dict[int, list] = {}
        self._teacher = Teacher.of_run(run) if t.dagger else None
        # with DAgger labels, demonstration games follow them; without, the planner's path from the start
        for i in range(0 if t.dagger else self._demo_games):
            self._plan(i)

    def make_module(self) -> None:
        self.module = self.config.get_multi_rl_module_spec(spaces=self.get_spaces(), inference_only=True).build()

    def get_spaces(self) -> dict:
        obs, act = spaces_of(self.run)
        agents = self.run.game.agent_names
        single = (gym.spaces.Dict({a: obs for a in agents}), gym.spaces.Dict({a: act for a in agents}))
        return {INPUT_ENV_SPACES: single, INPUT_ENV_SINGLE_SPACES: single,
                **{m: (obs, act) for m in set(self._modules_of_agent)}}

    def assert_healthy(self) -> None:
        assert self.module is not None and self.rollout is not None

    def set_replay(self, handle) -> bool:
        self._replay = handle
        return True

    # -- sampling
    def _plan(self, game: int) -> None:
        from formation.planner import shortest_path

        path = shortest_path(self.rollout.game.scenario(game), config=self.run.game)
        self._plans[game] = list(path or [])

    def _teacher_joints(self) -> np.ndarray:
        """DAgger: the teacher's joint action in every game's present state, -1 where it has none."""
        game, joints = self.rollout.game, np.full((self.rollout.batch_size, self.rollout.n_agents), -1, np.int8)
        scenarios = [game.scenario(i) for i in range(self.rollout.batch_size)]
        for i, joint in enumerate(self._teacher.labels(scenarios, list(game.steps == 0))):
            if joint is not None:
                joints[i] = joint
        return joints

    def _safe(self) -> np.ndarray:
        """``train.safety_horizon``: what the safety head learns of every game's present state
        (``teacher.safety_labels``)."""
        game = self.rollout.game
        return safety_labels([game.scenario(i) for i in range(game.batch_size)], game.config,
                             self.run.train.safety_horizon)

    def _labels(self, joints: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The labels to learn from, and the answers (``Chunk``) or None: the teacher's ``joints``; with
        ``train.follower_answers_leader`` the teacher's answer to the move the leader plays (``actions``), -1
        for the followers where no move of theirs survives it; with ``train.answer_every_leader_move`` also
        its answers to every move the leader could have made."""
        t, game = self.run.train, self.rollout.game
        if not t.follower_answers_leader:
            return joints, None
        labels = joints.copy()
        leader = actions[:, 0]
        if t.answer_every_leader_move:
            answers = np.full((*joints.shape, len(MOVES)), -1, np.int8)
            for i in np.flatnonzero(joints[:, 0] >= 0):
                scenario, joint = game.scenario(i), tuple(int(a) for a in joints[i])
                for move, answer in enumerate(self._teacher.answers(scenario, joint)):
                    if answer is not None:
                        answers[i, 1:, move] = answer[1:]
                labels[i, 1:] = answers[i, 1:, leader[i]]
            return labels, answers
        # where the leader makes the teacher's move, the label stands as it is
        for i in np.flatnonzero((joints[:, 0] >= 0) & (leader != joints[:, 0])):
            answer = self._teacher.answer(game.scenario(i), tuple(int(a) for a in joints[i]), int(leader[i]))
            labels[i, 1:] = answer[1:] if answer is not None else -1
        return labels, None

    def _actions(self, observations: np.ndarray) -> np.ndarray:
        """The epsilon-greedy actions (games, agents) to play. Followers that answer the leader
        (``train.follower_answers_leader``) answer the move the leader plays, and explore on their own only
        with ``train.exploration: independent``."""
        t, modules = self.run.train, self._modules_of_agent
        with torch.no_grad():
            q = q_values_of({m: self.module[m].q_network for m in sorted(set(modules))},
                            torch.from_numpy(observations))
        q = {m: v.numpy() for m, v in q.items()}
        greedy = team_q_values(q, modules).argmax(-1)
        epsilon = epsilon_at(self.num_env_steps_sampled_lifetime, t)
        if not t.follower_answers_leader:
            return epsilon_greedy(greedy, epsilon, self._rng, joint=t.exploration == "joint")
        leader = epsilon_greedy(greedy[:, :1], epsilon, self._rng, joint=False)[:, 0]
        actions = team_q_values(q, modules, leader_moves=leader).argmax(-1)
        actions[:, 0] = leader  # its own column holds its greedy move
        if t.exploration == "independent":
            actions[:, 1:] = epsilon_greedy(actions[:, 1:], epsilon, self._rng, joint=False)
        return actions

    def sample(self, **kwargs) -> dict[str, Any]:
        run, rollout, clock = self.run, self.rollout, self.clock
        chunks = []
        for _ in range(run.train.steps_per_sample):
            with clock("act"):
                actions = self._actions(rollout.observations)
            with clock("teacher"):
                if run.train.dagger:
                    joints = self._teacher_joints()
                else:
                    labels = np.full(actions.shape, -1, np.int8)
                for i in range(self._demo_games):  # demonstration games follow the teacher
                    if run.train.dagger:
                        actions[i] = np.where(joints[i] >= 0, joints[i], actions[i])
                    elif self._plans[i]:
                        actions[i] = labels[i] = self._plans[i].pop(0)
                answers = None
                if run.train.dagger:
                    labels, answers = self._labels(joints, actions)
            with clock("safety"):
                safe = self._safe() if run.train.safety_head else None
            with clock("game"):
                chunks.append(rollout.step(actions, labels=labels, answers=answers, safe=safe))
            if not run.train.dagger:
                with clock("teacher"):
                    for i in np.flatnonzero(rollout.game.steps[: self._demo_games] == 0):
                        self._plan(int(i))
        with clock("push"):
            records = concatenate(chunks)
            self._replay.add.remote(records)
        steps = rollout.batch_size * run.train.steps_per_sample
        self.num_env_steps_sampled_lifetime += steps
        episodes = rollout.pop_episodes()
        return {"env_steps": steps, "episodes": episodes, "worker": getattr(self, "worker_index", 0),
                "seconds": clock.pop()}

    # -- state
    def get_state(self, components=None, *, not_components=None, **kwargs) -> dict:
        state = {NUM_ENV_STEPS_SAMPLED_LIFETIME: self.num_env_steps_sampled_lifetime}
        if self._check_component(COMPONENT_RL_MODULE, components, not_components):
            state[COMPONENT_RL_MODULE] = self.module.get_state(
                components=self._get_subcomponents(COMPONENT_RL_MODULE, components),
                not_components=self._get_subcomponents(COMPONENT_RL_MODULE, not_components), **kwargs)
            state[WEIGHTS_SEQ_NO] = self._weights_seq_no
        return state

    def set_state(self, state: dict) -> None:
        with self.clock("sync"):
            self._set_state(state)

    def _set_state(self, state: dict) -> None:
        if COMPONENT_RL_MODULE in state:
            seq = state.get(WEIGHTS_SEQ_NO, 0)
            if seq == 0 or seq > self._weights_seq_no:
                weights = state[COMPONENT_RL_MODULE]
                if isinstance(weights, ray.ObjectRef):  # refs nested in a dict are not resolved by Ray
                    weights = ray.get(weights)
                self.module.set_state(weights)
            self._weights_seq_no = max(self._weights_seq_no, seq)
        if NUM_ENV_STEPS_SAMPLED_LIFETIME in state:
            self.num_env_steps_sampled_lifetime = int(state[NUM_ENV_STEPS_SAMPLED_LIFETIME])

    def get_ctor_args_and_kwargs(self):
        return (), {"config": self.config}

    def get_metrics(self) -> dict:
        return {}

    def stop(self) -> None:
        pass
