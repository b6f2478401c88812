"""The team as training builds it: each agent's module, the spaces every agent sees and acts in, and each
module's network (``NetworkSpec``), from the run's config. No Ray: the RLlib modules, the rollout actors and
``formation.policy`` all read these."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np

from formation.game.render import GRID_PLANES
from formation.recipe.config import RunConfig
from formation.recipe.qnet import NetworkSpec


def spaces_of(run: RunConfig) -> tuple[gym.spaces.Box, gym.spaces.Discrete]:
    from formation.game import BatchedGame, Observer

    observer = Observer(BatchedGame(run.game, batch_size=1))
    return gym.spaces.Box(0, observer.high, observer.shape, np.uint8), gym.spaces.Discrete(4)


def reads_cells(run: RunConfig) -> bool:
    """Whether the networks read screens one pixel per cell (``train.screen_cells`` on pixels): then the
    rollouts record, and the replay stores, only those cells (``GameRollout``'s ``screen_cells``)."""
    return run.game.obs_type == "pixels" and run.train.screen_cells


def replay_frame_shape(run: RunConfig) -> tuple[int, int, int]:
    """The shape of one frame the replay stores, as ``GameRollout.frame_shape`` of the run's rollouts: a
    screen's cells (``reads_cells``), else a frame of the observation (a screen or a grid)."""
    obs_space, _ = spaces_of(run)
    h, w, c = (int(v) for v in obs_space.shape)
    c //= run.game.frame_stack
    return (run.game.height, run.game.width, c) if reads_cells(run) else (h, w, c)


def module_of_agent(run: RunConfig) -> list[str]:
    """The module (policy) id of each agent, leader first: the followers share one."""
    return ["leader"] + ["follower"] * run.game.n_followers


def answers_leader(run: RunConfig, module: str) -> bool:
    """Whether ``module``'s network answers the leader (``train.follower_answers_leader``): every
    module but the leader's."""
    return run.train.follower_answers_leader and module != module_of_agent(run)[0]


def roles_of(run: RunConfig, module: str) -> int:
    """The roles of ``module``'s network (``NetworkSpec.roles``): the number of its agents where several share it
    (the followers of a team of two or more; with a ``games`` section, of its largest team), 0 for a network of one
    agent. RLlib's own DQN (``train.path: stock``) gives its modules no role input."""
    agents = module_of_agent(run).count(module)
    if run.games is not None and agents:
        agents = max(run.games.followers) if module != module_of_agent(run)[0] else 1
    return agents if agents > 1 and run.train.path == "formation" else 0


def network_specs(run: RunConfig) -> dict[str, NetworkSpec]:
    """Each module's network. ``train.leader_window`` (in cells) becomes the network's ``window`` (in entries of
    what it reads: cells of a grid or of a screen read per cell, pixels of a screen) and ``frame_channels``;
    ``train.screen_cells`` becomes ``cells``, the board's height and width."""
    t, game = run.train, run.game
    obs_space, _ = spaces_of(run)
    shape = tuple(int(v) for v in obs_space.shape)
    per_cell = reads_cells(run)
    window, frame_channels = t.leader_window, None
    if window is not None:
        frame_channels = len(GRID_PLANES) if game.obs_type == "grid" else 3
        if game.obs_type == "pixels" and not per_cell:
            up, down, side = window
            rows, cols = shape[0] / game.height, shape[1] / game.width  # pixels per cell
            # the leader's block of pixels starts at its top-left pixel: the window reaches one cell further down
            # and right
            window = (math.ceil(up * rows), math.ceil((down + 1) * rows), math.ceil((side + 1) * cols))
    return {m: NetworkSpec(obs_shape=shape, high=float(obs_space.high.max()), hidden=t.hidden, channels=t.channels,
                           window=window, compass=t.destination_compass, frame_channels=frame_channels,
                           cells=(game.height, game.width) if per_cell else None, forecast=t.obstacle_forecast,
                           answers_leader=answers_leader(run, m), safety=run.safety_head,
                           safety_encoder=run.safety_head and run.teacher.safety_encoder, roles=roles_of(run, m))
            for m in sorted(set(module_of_agent(run)))}
