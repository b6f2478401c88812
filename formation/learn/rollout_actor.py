"""Rollout actors: RLlib EnvRunners that play a batch of games and push records to the replay.

Each ``sample()`` plays ``steps_per_sample`` steps of all its games with the weights it was last
sent (epsilon-greedy per agent), pushes the records straight to its replay shard and returns
only counts and finished-episode statistics, never transitions.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import ray
import torch
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.core.columns import Columns
from ray.rllib.env import INPUT_ENV_SINGLE_SPACES, INPUT_ENV_SPACES
from ray.rllib.env.env_runner import EnvRunner
from ray.rllib.utils.checkpoints import Checkpointable
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME, WEIGHTS_SEQ_NO

from formation.learn.config import RunConfig
from formation.learn.rollout import GameRollout, concatenate
from formation.learn.shaping import Potential


def spaces_of(run: RunConfig) -> tuple[gym.spaces.Box, gym.spaces.Discrete]:
    from formation.game import BatchedGame, Observer

    observer = Observer(BatchedGame(run.game, batch_size=1))
    return gym.spaces.Box(0, observer.high, observer.shape, np.uint8), gym.spaces.Discrete(4)


def module_of_agent(run: RunConfig) -> list[str]:
    """The module (policy) id of each agent, leader first."""
    names = run.game.agent_names
    if run.train.followers_share_policy:
        return ["leader"] + ["follower"] * run.game.n_followers
    return names


class RolloutActor(EnvRunner, Checkpointable):
    def __init__(self, *, config, **kwargs):
        super().__init__(config=config, **kwargs)
        torch.set_num_threads(1)
        self.run = RunConfig.from_dict(self.config.formation_run)
        self._modules_of_agent = module_of_agent(self.run)
        self._weights_seq_no = 0
        self._replay = None
        self.num_env_steps_sampled_lifetime = 0
        self.make_env()
        self.make_module()

    # -- RLlib's EnvRunner API
    def make_env(self) -> None:
        run = self.run
        index = getattr(self, "worker_index", 0) or 0
        games = run.resources.games_per_actor
        t = run.train
        potential = Potential(t.potential, run.game, t.planner_slack) if t.shaping > 0 and t.potential != "none" \
            else None
        self.rollout = GameRollout(run.game, games, seed=t.seed * 10_007 + index, stream_offset=index * games,
                                   potential=potential, shaping=t.shaping, gamma=t.gamma)
        self._demo_games = int(round(run.train.demonstrations * games))
        self._plans: dict[int, list] = {}
        for i in range(self._demo_games):
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

    def _actions(self, observations: np.ndarray) -> np.ndarray:
        obs = torch.from_numpy(observations)
        by_module = {}
        with torch.no_grad():
            for m in set(self._modules_of_agent):
                out = self.module[m].forward_exploration({Columns.OBS: obs}, t=self.num_env_steps_sampled_lifetime)
                by_module[m] = out[Columns.ACTIONS].numpy()
        actions = np.stack([by_module[m] for m in self._modules_of_agent], axis=1)
        if len({*self._modules_of_agent}) < len(self._modules_of_agent):
            # followers sharing one policy still explore independently
            shared = [i for i, m in enumerate(self._modules_of_agent) if self._modules_of_agent.count(m) > 1]
            for i in shared[1:]:
                redo = self.module[self._modules_of_agent[i]].forward_exploration(
                    {Columns.OBS: obs}, t=self.num_env_steps_sampled_lifetime)
                actions[:, i] = redo[Columns.ACTIONS].numpy()
        return actions

    def sample(self, **kwargs) -> dict[str, Any]:
        run, rollout = self.run, self.rollout
        chunks = []
        expert = np.zeros(rollout.batch_size, bool)
        expert[: self._demo_games] = True
        for _ in range(run.train.steps_per_sample):
            actions = self._actions(rollout.observations)
            for i in range(self._demo_games):
                if self._plans[i]:
                    actions[i] = self._plans[i].pop(0)
            chunk = rollout.step(actions, expert=expert)
            chunks.append(chunk)
            for i in np.flatnonzero(rollout.game.steps[: self._demo_games] == 0):
                self._plan(int(i))
        records = concatenate(chunks)
        steps = rollout.batch_size * run.train.steps_per_sample
        self.num_env_steps_sampled_lifetime += steps
        self._replay.add.remote(records)
        episodes = rollout.pop_episodes()
        return {"env_steps": steps, "episodes": episodes, "worker": getattr(self, "worker_index", 0)}

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
