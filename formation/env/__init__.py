"""Views of the game for RL libraries: PettingZoo's ``formation_v2`` (parallel and AEC; its card is
the docstring of ``formation.env.pettingzoo``). RLlib's ``MultiAgentEnv`` is ``formation.rllib.env``: nothing
here imports Ray."""

from __future__ import annotations

from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec

from formation.config import ConfigError, GameConfig
from formation.env.pettingzoo import FormationParallelEnv


def parallel_env(setting: int | None = 1, render_mode: str | None = None, **overrides: Any) -> FormationParallelEnv:
    """The PettingZoo ``ParallelEnv`` of a named setting (1-4) with ``GameConfig`` overrides."""
    return FormationParallelEnv(GameConfig.from_setting(setting, **overrides), render_mode=render_mode)


def env(setting: int | None = 1, render_mode: str | None = None, **overrides: Any):
    """The AEC form, through PettingZoo's own conversion."""
    return parallel_to_aec(parallel_env(setting, render_mode=render_mode, **overrides))


__all__ = ["ConfigError", "FormationParallelEnv", "GameConfig", "env", "parallel_env"]
