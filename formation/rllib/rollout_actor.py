"""Rollout actors: RLlib EnvRunners around the recipe's ``Collector``, pushing its records to the replay.

Each ``sample()`` has the collector play ``steps_per_sample`` steps of all its games with the weights it was last
sent (``formation.recipe.collect``), pushes the records straight to its replay shard and returns only counts and
its finished episodes' metrics, reduced in the actor as RLlib's EnvRunners reduce theirs, never transitions. The
actor holds no recipe of its own: it moves weights in and records out.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import ray
import torch
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.env import INPUT_ENV_SINGLE_SPACES, INPUT_ENV_SPACES
from ray.rllib.env.env_runner import EnvRunner
from ray.rllib.utils.checkpoints import Checkpointable
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    EPISODE_AGENT_RETURN_MEAN,
    EPISODE_LEN_MEAN,
    EPISODE_MODULE_RETURN_MEAN,
    EPISODE_RETURN_MAX,
    EPISODE_RETURN_MEAN,
    EPISODE_RETURN_MIN,
    NUM_ENV_STEPS_SAMPLED,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_EPISODES,
    WEIGHTS_SEQ_NO,
)

from formation.recipe.collect import Collector
from formation.recipe.rollout import STARTS
from formation.recipe.stopwatch import Stopwatch, add_seconds, with_size
from formation.recipe.team import module_of_agent, spaces_of

ADDS_IN_FLIGHT = 2  # pushes a rollout actor may have unacknowledged before it waits for its replay shard


class RolloutActor(EnvRunner, Checkpointable):
    def __init__(self, *, config, **kwargs):
        super().__init__(config=config, **kwargs)
        torch.set_num_threads(1)
        self.run = self.config.run  # the run config, the RLlib fields that name its keys merged in
        self._modules_of_agent = module_of_agent(self.run)
        self._weights_seq_no = 0
        self._replay = None
        self._adds: list = []  # pushes to the replay not yet acknowledged
        self.num_env_steps_sampled_lifetime = 0
        self.clock = Stopwatch()  # seconds per stage, returned with every sample()
        self.make_env()
        self.make_module()

    # -- RLlib's EnvRunner API
    def make_env(self) -> None:
        self.collector = Collector(self.run, getattr(self, "worker_index", 0) or 0)
        self.rollout = self.collector.rollout

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
        self._replay, self._adds = handle, []
        return True

    # -- sampling
    def sample(self, **kwargs) -> dict[str, Any]:
        networks = {m: self.module[m].q_network for m in sorted(set(self._modules_of_agent))}
        records, episodes = self.collector.collect(networks, self.run.train.steps_per_sample,
                                                   self.num_env_steps_sampled_lifetime)
        with self.clock("push"):
            self._adds.append(self._replay.add.remote(records))
        if len(self._adds) > ADDS_IN_FLIGHT:  # a replay that falls behind slows its actors, not the object store's
            with self.clock("push_wait"):
                _, self._adds = ray.wait(self._adds, num_returns=len(self._adds) - ADDS_IN_FLIGHT)
        steps = self.rollout.batch_size * self.run.train.steps_per_sample
        self.num_env_steps_sampled_lifetime += steps
        log_episodes(self.metrics, episodes, steps, self.run, self.config.metrics_num_episodes_for_smoothing)
        return with_size({"env_steps": steps, "episodes": len(episodes), "metrics": self.metrics.reduce(),
                          "worker": getattr(self, "worker_index", 0),
                          "seconds": add_seconds(self.collector.clock.pop(), self.clock.pop())})

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


def no_episodes_yet(run, window: int) -> dict:
    """A rollout actor's reduced metrics before any sample: counts of 0, means NaN (which RLlib's means pass over),
    so that RLlib's ``env_runners`` keys are in every result from the first on (Tune's metric checks need them)."""
    from ray.rllib.utils.metrics.metrics_logger import MetricsLogger

    metrics = MetricsLogger()
    log_episodes(metrics, [], 0, run, window)
    return metrics.reduce()


def log_episodes(m, episodes: list[dict], env_steps: int, run, window: int) -> None:
    """A sample's finished episodes into the rollout actor's ``MetricsLogger`` ``m``, as RLlib's EnvRunners log
    theirs: its standard ``env_runners`` keys (an episode's return is its agents' summed, as RLlib's multi-agent
    episodes count it) and the recipe's ``explore`` rates. Reduced in the actor and merged by the driver
    (``MetricsLogger.aggregate``): the driver handles one small record per sample instead of a dozen values per
    episode."""
    # Ray 2.60's windowed means are emptied at each iteration's reduce: every mean below is over the episodes
    # that ended in this iteration (NaN in one that ended none); the windows only cap how many count
    agents, modules = run.game.agent_names, module_of_agent(run)
    m.log_value((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED), env_steps, reduce="sum")
    m.log_value((ENV_RUNNER_RESULTS, NUM_EPISODES), len(episodes), reduce="sum")
    if not episodes and not env_steps:  # no_episodes_yet: the means' keys, NaN (RLlib's means pass over NaN)
        for key in (EPISODE_RETURN_MEAN, EPISODE_LEN_MEAN):
            m.log_value((ENV_RUNNER_RESULTS, key), math.nan, window=window)
    for e in episodes:
        team = float(sum(e["returns"]))
        m.log_value((ENV_RUNNER_RESULTS, EPISODE_RETURN_MEAN), team, window=window)
        m.log_value((ENV_RUNNER_RESULTS, EPISODE_RETURN_MAX), team, reduce="max", window=window)
        m.log_value((ENV_RUNNER_RESULTS, EPISODE_RETURN_MIN), team, reduce="min", window=window)
        m.log_value((ENV_RUNNER_RESULTS, EPISODE_LEN_MEAN), e["steps"], window=window)
        for module in set(modules):
            value = sum(r for r, owner in zip(e["returns"], modules) if owner == module)
            m.log_value((ENV_RUNNER_RESULTS, EPISODE_MODULE_RETURN_MEAN, module), value, window=window)
        for name, value in zip(agents, e["returns"]):
            m.log_value((ENV_RUNNER_RESULTS, EPISODE_AGENT_RETURN_MEAN, name), value, window=window)
            m.log_value(("explore", f"return_{name}"), value, window=500)
        for key in ("success", "reached", "collided", "broken", "truncated"):
            m.log_value(("explore", key), float(e[key]), window=500)
        m.log_value(("explore", "episode_steps"), e["steps"], window=500)
        for start in STARTS[1:]:  # the share of training episodes that started elsewhere than the spec's places
            m.log_value(("explore", f"start_{start}"), float(e["start"] == start), window=500)
