"""Formation, the PettingZoo environment (``formation_v2``).

| | |
| --- | --- |
| import | ``from formation.env import parallel_env, env`` |
| actions | simultaneous |
| parallel API | yes (``parallel_env``; ``env()`` is PettingZoo's AEC conversion of it) |
| manual control | no |
| agents | ``agents = ["leader", "follower"]``; ``["leader", "follower_1", .., "follower_k"]`` with ``n_followers=k`` |
| number of agents | ``1 + n_followers`` (2 by default; default starts for 1-4 followers, docs/GAME.md) |
| action shape | ``Discrete(4)``: 0 F (forward), 1 FL (left forward), 2 FR (right forward), 3 S (stay) |
| observation shape | ``(84, 84, 3*frame_stack)``: the last ``frame_stack`` RGB screens, oldest first |
| observation values | ``uint8`` in ``[0, 255]``; with ``obs_type="grid"``: ``(H, W, 4*frame_stack)`` in ``[0, 1]`` |
| state shape | ``(84, 84, 3)``: the present screen; with ``obs_type="grid"``: ``(H, W, 4)``, the present grid |
| state values | ``uint8`` in ``[0, 255]``; grid: ``[0, 1]`` |
| render modes | ``None``, ``"rgb_array"`` (the present screen whatever the observation type) |
| rules | ``docs/GAME.md`` (rules v2) |

Every agent observes the same full screen. ``state()`` is the global state as one frame of the
observation type, unstacked: the screen the renderer draws for the present game (pixels), or its
four 0/1 planes destination, obstacles, followers, leader (grid). It is what every agent's newest
observation frame shows, so with ``frame_stack=1`` it equals each agent's observation.
``state_space`` is the ``Box`` it lies in.

Arguments: ``parallel_env(setting=1, render_mode=None, **overrides)``: ``setting`` is a named setting
(1-4, ``None`` for the plain defaults) and ``overrides`` any ``GameConfig`` field, for example
``obs_type`` (``"pixels"``, ``"grid"``), ``frame_stack`` (4), ``n_followers`` (1), ``n_obstacles``,
``max_steps`` (200), ``height``, ``width``, ``formation``, ``d_min``, ``d_max`` and the reward weights.

``reset(options={"scenario": S})`` starts from a scenario; ``env.scenario()`` reads the present
one. Infos per agent: ``position``, ``collided``, ``formation_kept``, ``distance`` (a follower's own
distance to the leader; the leader's is the distance to its farthest follower), ``reached``,
``success``, ``steps``.

Version history:
* v2: horizontal teams of 3 and 4 followers start beside and behind the leader, which starts two rows up
  (rules v2); every other game as in v1.
* v1: ``state()`` and ``state_space`` (the present screen or grid); the same game (rules v1); default starts
  for teams of 3 and 4 followers.
* v0: initial release, rules v1.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame, Observer, ScreenRenderer


class FormationParallelEnv(ParallelEnv):
    metadata = {"name": "formation_v2", "render_modes": ["rgb_array"], "render_fps": 8,
                "is_parallelizable": True}

    def __init__(self, config: GameConfig | None = None, render_mode: str | None = None):
        self.config = config = config or GameConfig()
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode: {render_mode!r} is not allowed; allowed: None, 'rgb_array'")
        self.render_mode = render_mode
        self.possible_agents = config.agent_names
        self.agents: list[str] = []
        self.game = BatchedGame(config, batch_size=1)
        self.game.reset()
        self._observer = Observer(self.game)
        self._screen: ScreenRenderer | None = None
        box = spaces.Box(0, self._observer.high, self._observer.shape, np.uint8)
        self.observation_spaces = {a: box for a in self.possible_agents}
        self.action_spaces = {a: spaces.Discrete(4) for a in self.possible_agents}
        self.state_space = spaces.Box(0, self._observer.high, self._observer.frame_shape, np.uint8)
        self._reset_flag = np.ones(1, bool)

    def observation_space(self, agent: str) -> spaces.Space:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        # Other option keys are ignored: PettingZoo's parallel_api_test passes {"options": 1}.
        options = options or {}
        if options.get("scenario") is not None:
            if seed is not None:
                self.game.rng = np.random.default_rng(seed)
            self.game.load([options["scenario"]])
        else:
            self.game.reset(seed=seed)
        self.agents = list(self.possible_agents)
        obs = self._observe(reset=True)
        return obs, self._infos()

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: missing an action for {missing}; every live agent acts each step")
        joint = np.array([[int(actions[a]) for a in self.possible_agents]], dtype=np.intp)
        if ((joint < 0) | (joint > 3)).any():
            raise ValueError(f"actions: {dict(actions)} has a value outside 0..3")
        g = self.game
        g.step(joint)
        obs = self._observe(reset=False)
        rewards = dict(zip(self.possible_agents, g.rewards[0].tolist()))
        term, trunc = bool(g.terminated[0]), bool(g.truncated[0])
        terminations = {a: term for a in self.possible_agents}
        truncations = {a: trunc for a in self.possible_agents}
        infos = self._infos()
        if term or trunc:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        """The global state: the present frame of the observation type, unstacked (see the card)."""
        # The observer renders on every reset and step, so its last frame is the present one.
        return self._observer.renderer.frames[0].copy()

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        return self.screen()

    def close(self) -> None:
        pass

    # ------------------------------------------------------------------ extras
    def scenario(self) -> dict[str, Any]:
        """The present state as a scenario dict; resetting with it reproduces the future exactly."""
        return self.game.scenario(0).to_dict()

    def screen(self) -> np.ndarray:
        """The present 84x84x3 RGB screen, whatever the observation type."""
        if self.config.obs_type == "pixels":
            return self._observer.renderer.screens[0].copy()
        if self._screen is None:
            self._screen = ScreenRenderer(self.game)
        return self._screen.render()[0].copy()

    def _observe(self, reset: bool) -> dict[str, np.ndarray]:
        self._reset_flag[0] = reset
        obs = self._observer.observe(self._reset_flag)[0].copy()
        return {a: obs for a in self.possible_agents}

    def _infos(self) -> dict[str, dict[str, Any]]:
        g = self.game
        positions = g.positions[0].tolist()
        collided = g.collided[0].tolist()
        distances = g.distances[0].tolist()
        common = {"formation_kept": bool(g.formation_kept[0]), "reached": bool(g.reached[0]),
                  "success": bool(g.success[0]), "steps": int(g.steps[0])}
        infos = {}
        for i, agent in enumerate(self.possible_agents):
            distance = max(distances) if i == 0 else distances[i - 1]
            infos[agent] = {"position": positions[i], "collided": collided[i], "distance": distance, **common}
        return infos
