"""The RLlib view of the game: a ``MultiAgentEnv`` over the PettingZoo environment, registered as ``"formation"``.

``env_config`` is a dict of ``GameConfig`` fields plus ``setting``; e.g.
``config.environment("formation", env_config={"setting": 2, "obs_type": "grid"})``.
"""

from __future__ import annotations

from typing import Any

from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.tune.registry import register_env

from formation.config import GameConfig
from formation.env.pettingzoo import FormationParallelEnv

ENV_NAME = "formation"


class FormationMultiAgentEnv(MultiAgentEnv):
    def __init__(self, env_config: dict[str, Any] | None = None):
        super().__init__()
        config = dict(env_config or {})
        self.config = GameConfig.from_dict(config)
        self.env = FormationParallelEnv(self.config)
        self.possible_agents = list(self.env.possible_agents)
        self.agents = list(self.possible_agents)
        self.observation_spaces = dict(self.env.observation_spaces)
        self.action_spaces = dict(self.env.action_spaces)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return obs, infos

    def step(self, action_dict: dict[str, Any]):
        obs, rewards, terms, truncs, infos = self.env.step(action_dict)
        terms["__all__"] = all(terms.values())
        truncs["__all__"] = all(truncs.values())
        # ``agents`` stays as it was until the next reset (as in RLlib's ParallelPettingZooEnv):
        # RLlib's env checker matches the last step's dict keys against it.
        return obs, rewards, terms, truncs, infos

    def scenario(self) -> dict[str, Any]:
        return self.env.scenario()


def register() -> str:
    """Register the env with Ray Tune's registry under ``ENV_NAME``; returns the name."""
    register_env(ENV_NAME, lambda env_config: FormationMultiAgentEnv(dict(env_config)))
    return ENV_NAME
