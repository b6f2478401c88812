"""The Q-network, in plain torch (the RLlib module wraps it; ``formation.recipe.loss`` holds the DQN arithmetic).

Observations arrive as uint8 ``(N, H, W, C)`` (C = frame channels x stack) and are normalised
here. The encoders are sized for CPUs: the pixel encoder's first layer reads non-overlapping
4x4 patches, so a forward pass costs about 2.4 MMAC per sample instead of the Nature DQN's 10.

With a ``LeaderWindow`` the network first shifts every frame of the stack so that the leader sits
at a fixed place and keeps a window around it (the board's edge marked by a plane of its own):
what is near the leader then lands on the same inputs wherever the team is, and a rule learnt in
one place holds in every other (docs/lab/TRAINING.md measures what that is worth).

With a ``ScreenCells`` reader the network first takes one pixel per cell of the board from each
screen (the renderer paints a whole cell in one colour, so nothing on the screen is lost) and
reads the result as a grid, at one entry per cell: on settings 3-4 a cell is 1.68 pixels wide,
and 4x4 patches would mix two or three cells. Such a network also reads cells taken already (the
replay stores only those, ``formation.recipe.rollout.GameRollout``) and gives the same outputs as on
the whole screens.

A network that *answers the leader* (a follower's, ``train.follower_answers_leader``) outputs one
Q-value per pair (leader's move, own move), 16 in all, row by row: the follower picks its move in
the row of the move the leader makes (``team_q_values``).

A network that several agents share (the followers of a team of two or more) takes each agent's index among them,
its *role*, as input: a one-hot code beside the encoder's features, read by both heads (as parameter-sharing MARL
gives every agent its id). All agents see the same screen, so the encoder runs once and the heads once per role:
such a network outputs ``(N, roles, outputs)``, every role's Q-values of the same screens (``agent_roles``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from formation.config import ConfigError
from formation.game.render import cell_pixels
from formation.recipe.config import drop_removed

N_ACTIONS = 4


def encoder(obs_shape: tuple[int, int, int], channels: tuple[int, int, int] = (16, 32, 32),
            screens: bool | None = None) -> nn.Sequential:
    h, w, c = obs_shape
    c1, c2, c3 = channels
    if screens if screens is not None else min(h, w) >= 64:  # screens: 84x84 -> 21 -> 11 -> 6
        first = nn.Conv2d(c, c1, kernel_size=4, stride=4)
    else:  # grids: one cell per entry, keep full resolution in the first layer
        first = nn.Conv2d(c, c1, kernel_size=3, stride=1, padding=1)
    return nn.Sequential(first, nn.ReLU(), nn.Conv2d(c1, c2, 3, 2, 1), nn.ReLU(), nn.Conv2d(c2, c3, 3, 2, 1),
                         nn.ReLU(), nn.Flatten())


def dueling(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Q(s, a) = V(s) + A(s, a) - mean_a' A(s, a')   (Wang et al. 2016, eq. 9; the paper's dueling head)."""
    return value + advantage - advantage.mean(dim=-1, keepdim=True)


def team_q_values(q: dict[str, np.ndarray], modules: list[str], leader_moves: np.ndarray | None = None
                  ) -> np.ndarray:
    """Every agent's Q-values of its four moves, (N, agents, 4), from each module's output ``q``
    (module -> (N, 4), or (N, 16) for a module that answers the leader); ``modules``: each agent's
    module, leader first. An answering module's agents read the row of ``leader_moves``, the moves the
    leader makes (N,); None: the leader's greedy moves, which a follower computes from its own screen
    with the leader's network, since both see the same."""
    if leader_moves is None:
        leader_moves = q[modules[0]].argmax(-1)
    rows = np.arange(len(leader_moves))

    def answered(v: np.ndarray) -> np.ndarray:
        return v.reshape(-1, N_ACTIONS, N_ACTIONS)[rows, leader_moves] if v.shape[-1] == N_ACTIONS ** 2 else v

    # a network of several roles (N, roles, outputs): each agent reads its own role's
    return np.stack([answered(q[m][:, role] if q[m].ndim == 3 else q[m])
                     for m, role in zip(modules, agent_roles(modules))], axis=1)


def of_role(q: torch.Tensor, role: torch.Tensor | None) -> torch.Tensor:
    """(N, outputs): each sample's Q-values for the agent of its ``role`` (N,), from a network's ``q``; the
    Q-values of a network without roles, (N, outputs), as they are."""
    return q if q.dim() == 2 else q[torch.arange(len(q), device=q.device), role.long()]


def agent_roles(modules: list[str]) -> list[int]:
    """Each agent's role, its index among the agents of its module (``modules``: each agent's module, leader
    first): follower ``i`` of a team whose followers share a network has role ``i - 1``."""
    seen: dict[str, int] = {}
    roles = []
    for m in modules:
        roles.append(seen.get(m, 0))
        seen[m] = roles[-1] + 1
    return roles


def first_entry(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, H, W)`` bool -> (N,) long, the row-major index of each sample's first True entry (0 where there is
    none), and (N,) bool, whether there is one."""
    flat = mask.reshape(mask.shape[0], -1)
    return flat.float().argmax(1), flat.any(1)


def leader_entry(obs: torch.Tensor, frame_channels: int, screens: bool) -> torch.Tensor:
    """(N,) long: the row-major index of the leader's top-left entry in the newest frame (the last
    ``frame_channels`` channels) of uint8 observations ``(N, H, W, C)``: on a grid its own plane (the
    frame's last), on a screen (or its cells) its colour, pure blue (drawn last, so never hidden)."""
    newest = obs[..., -frame_channels:]
    if screens:
        red, green, blue = newest[..., 0], newest[..., 1], newest[..., 2]
        mask = (blue > 127) & (red < 128) & (green < 128)
    else:
        mask = newest[..., -1] > 0  # GRID_PLANES: destination, obstacles, followers, leader
    return first_entry(mask)[0]


def destination_entry(obs: torch.Tensor, frame_channels: int, screens: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) long, (N,) bool: the row-major index of the destination's top-left entry in the newest frame of
    uint8 observations ``(N, H, W, C)`` (on a grid its own plane, the frame's first; on a screen or its cells,
    white), and whether it is in sight (an agent standing on it hides it)."""
    newest = obs[..., -frame_channels:]
    mask = (newest > 127).all(-1) if screens else newest[..., 0] > 0  # GRID_PLANES: destination first
    return first_entry(mask)


class LeaderWindow(nn.Module):
    """``(N, H, W, C)`` frame stacks -> ``(N, up + 1 + down, 2 * side + 1, C + 1)``: every frame shifted
    so that the leader's top-left entry in the newest frame sits at row ``up``, column ``side``;
    entries outside the board are 0, and the extra last plane is 1 on the board. The leader is found
    by ``leader_entry``.

    With ``compass`` one more plane, before the board's, marks the destination where it is in the window,
    and else the entry of the window's edge nearest to it: a leader far from the destination still knows
    which way it lies, at the cost of one input plane (a window that shows a 50x50 board's destination from
    anywhere costs the encoder several times its work).
    """

    def __init__(self, obs_shape: tuple[int, int, int], window: tuple[int, int, int], frame_channels: int,
                 screens: bool, compass: bool = False):
        super().__init__()
        self.h, self.w, self.c = obs_shape
        self.up, self.down, self.side = window
        self.frame_channels, self.screens, self.compass = frame_channels, screens, compass
        self.out_shape = (self.up + 1 + self.down, 2 * self.side + 1, self.c + 1 + int(compass))
        # window row i is board row (leader's row - up + i); column j, board column (leader's - side + j)
        self.register_buffer("rows", torch.arange(self.out_shape[0]), persistent=False)
        self.register_buffer("cols", torch.arange(self.out_shape[1]), persistent=False)

    def forward(self, obs: torch.Tensor, scale: float = 1.0, extra: torch.Tensor | None = None) -> torch.Tensor:
        """uint8 observations -> the window as floats: the observation's entries times ``scale``, then the
        planes of ``extra`` (floats on the same board, ``(N, H, W, E)``, cropped alike), and the board plane
        (1 on the board, 0 off it) last."""
        n, h, w, c = obs.shape
        where = leader_entry(obs, self.frame_channels, self.screens)  # row-major: the top-left entry
        rows = (where // w)[:, None] - self.up + self.rows  # (n, window rows): rows of the board
        cols = (where % w)[:, None] - self.side + self.cols
        board = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
        flat = (rows.clamp(0, h - 1)[:, :, None] * w + cols.clamp(0, w - 1)[:, None, :]).reshape(n, -1, 1)

        def crop(planes: torch.Tensor) -> torch.Tensor:
            k = planes.shape[3]
            picked = planes.reshape(n, h * w, k).gather(1, flat.expand(-1, -1, k))
            return picked.reshape(n, *self.out_shape[:2], k).float() * board[..., None]

        parts = [crop(obs) * scale] + ([crop(extra)] if extra is not None else [])
        if self.compass:
            parts.append(self.destination_plane(obs, where))
        return torch.cat([*parts, board[..., None].float()], dim=3)

    def destination_plane(self, obs: torch.Tensor, leader: torch.Tensor) -> torch.Tensor:
        """(N, window rows, window columns, 1): 1 at the destination, clamped into the window (``compass``)."""
        n, _, w, _ = obs.shape
        where, seen = destination_entry(obs, self.frame_channels, self.screens)
        rows, cols = self.out_shape[:2]
        row = (where // w - leader // w + self.up).clamp(0, rows - 1)
        col = (where % w - leader % w + self.side).clamp(0, cols - 1)
        plane = torch.zeros(n, rows * cols, device=obs.device)
        plane.scatter_(1, (row * cols + col)[:, None], seen.float()[:, None])
        return plane.reshape(n, rows, cols, 1)


class ScreenCells(nn.Module):
    """``(N, S, S, C)`` screens -> ``(N, height, width, C)``: the top-left pixel of every cell of a
    ``height`` x ``width`` board, where the screen's cells start (``cell_pixels``, spec 'Screen').

    Cells taken already, ``(N, height, width, C)``, pass unchanged: the replay stores only the cells, so
    the learner's batches hold them, while acting reads whole screens. The two shapes cannot be confused:
    a screen is 84x84, a board at most 50x50 (a board as large as its screen would have one pixel per
    cell, and reading all of them leaves the screen as it is)."""

    def __init__(self, obs_shape: tuple[int, int, int], board: tuple[int, int]):
        super().__init__()
        h, w, c = obs_shape
        height, width = board
        if height > h or width > w:
            raise ValueError(f"a {height}x{width} board has cells under one pixel on a {h}x{w} screen")
        self.out_shape = (height, width, c)
        self.register_buffer("rows", torch.as_tensor(cell_pixels(height, h)), persistent=False)
        self.register_buffer("cols", torch.as_tensor(cell_pixels(width, w)), persistent=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.shape[1:] == self.out_shape:  # cells taken already (the replay's)
            return obs
        return obs.index_select(1, self.rows).index_select(2, self.cols)


FORECAST_LAGS = (-1, 0, 1, 2, 3)


class ObstacleForecast(nn.Module):
    """``(N, H, W, C)`` cell stacks -> ``(N, H, W, len(lags))`` 0/1 floats: plane ``j`` marks the cells where
    an agent arriving at row ``x`` after ``max(leader's row - x + lags[j], 1)`` steps would collide (lag 0:
    the leader going forward every step; 1: after one stay; a follower two rows below arrives on lag 2).

    A fixed layer, no weights: each obstacle's column is read from the newest and the previous frame (the
    spec's reset draws at most one obstacle per row), its speed and direction are the ones of the game's
    rule of motion that carry the previous column to the newest, and its future sub-step cells follow that
    rule (spec 'One step': an obstacle bounces like a ball between columns 0 and W-1, which is a constant
    motion on a circle of 2(W-1) cells folded in two). Where no obstacle moved between the two frames (an
    episode's first screen, repeated), every speed and direction is marked. Screens must be read per cell.
    """

    def __init__(self, board: tuple[int, int], frame_channels: int, screens: bool,
                 lags: tuple[int, ...] = FORECAST_LAGS):
        super().__init__()
        self.height, self.width = board
        self.frame_channels, self.screens = frame_channels, screens
        self.period = max(2 * (self.width - 1), 1)
        # arrival lags of the planes, and one more either side for the rows above and below an obstacle
        self.register_buffer("lags", torch.arange(min(lags) - 1, max(lags) + 2), persistent=False)
        if tuple(range(min(lags), max(lags) + 1)) != tuple(lags):
            raise ValueError(f"lags: {lags} are not consecutive")
        # the hypotheses (direction, speed) an obstacle may have now: the spec's speeds 1 and 2 (the training
        # config refuses others, formation.recipe.config.FORECAST_SPEEDS)
        self.register_buffer("directions", torch.tensor([1, 1, -1, -1]), persistent=False)
        self.register_buffer("speeds", torch.tensor([1, 2, 1, 2]), persistent=False)
        self.register_buffer("rows", torch.arange(self.height), persistent=False)

    def obstacles(self, obs: torch.Tensor, frames_back: int) -> torch.Tensor:
        """(N, H, W) bool: obstacle cells of the frame ``frames_back`` before the newest."""
        start = obs.shape[3] - (frames_back + 1) * self.frame_channels
        if not self.screens:
            return obs[..., start + 1] > 0  # GRID_PLANES: destination, obstacles, followers, leader
        red, green, blue = obs[..., start], obs[..., start + 1], obs[..., start + 2]
        return (red > 127) & (green < 128) & (blue < 128)

    def fold(self, u: torch.Tensor) -> torch.Tensor:
        """A place on the circle of 2(W-1) cells -> its column."""
        return torch.where(u > self.width - 1, self.period - u, u)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        now, before = self.obstacles(obs, 0), self.obstacles(obs, 1)
        present, present_before = now.any(2), before.any(2)  # (N, H): rows holding an obstacle
        col, col_before = now.float().argmax(2), before.float().argmax(2)
        # each hypothesis' place on the circle now, and the column it came from
        place = torch.where(self.directions > 0, col[..., None], (self.period - col[..., None]) % self.period)
        came_from = self.fold((place - self.speeds) % self.period)
        fits = (came_from == col_before[..., None]) & present_before[..., None]  # (N, H, 4)
        still = ((col == col_before) | ~present).all(1)  # (N,): nothing moved, the first screen repeated
        unknown = still[:, None] | ~present_before
        allowed = (fits | unknown[..., None]) & present[..., None]
        leader_row = leader_entry(obs, self.frame_channels, self.screens) // self.width
        # steps until an agent on lag l reaches an obstacle's row; the cells the obstacle reaches on that step
        steps = (leader_row[:, None, None] - self.rows[None, :, None] + self.lags).clamp(min=1)[..., None]
        first = self.fold((place[:, :, None] + self.speeds * (steps - 1) + 1) % self.period)  # (N, H, L, 4)
        last = self.fold((place[:, :, None] + self.speeds * steps) % self.period)
        keep = allowed[:, :, None, :].expand_as(first).float()
        on = torch.zeros(*first.shape[:3], self.width, device=obs.device)
        on.scatter_add_(3, first, keep).scatter_add_(3, last, keep)
        on = on > 0  # (N, H, L, W): the cells reached
        near = on.clone()  # and those beside them in the row
        near[..., 1:] |= on[..., :-1]
        near[..., :-1] |= on[..., 1:]
        # rule 3: within distance 1 of a reached cell, in its row or right above or below it (an agent reaches
        # a row one step after the row below it)
        danger = near[:, :, 1:-1].clone()
        danger[:, 1:] |= on[:, :-1, :-2]
        danger[:, :-1] |= on[:, 1:, 2:]
        return danger.permute(0, 1, 3, 2).float()


@dataclass(frozen=True)
class NetworkSpec:
    """Everything a ``DuelingQNetwork`` is built from: what training's RLlib module builds, what a policy card
    stores (``networks.<module>``, ``to_dict``) and what loading a policy rebuilds (``from_dict``).

    ``obs_shape`` (H, W, C) and ``high`` (the largest observation value): what the network reads. ``window``
    (rows above, rows below, columns either side of the leader, in entries of the observation): look through
    a ``LeaderWindow`` first; None: the whole observation as it is. ``compass``: that window also marks where
    the destination lies (``LeaderWindow``, ``train.destination_compass``). ``frame_channels``: channels of
    one frame of the stack (None: 3 for screens, 4 for grids). ``cells`` (board height, width), screens only: read one
    pixel per cell first (``ScreenCells``; the cells of ``obs_shape``'s screens, taken already, are read as
    they are); ``window`` is then in cells, and the encoder's first layer reads every cell. ``forecast``: add
    the planes of an ``ObstacleForecast`` to what the encoder reads (grids, or screens read per cell, of two
    frames or more). ``answers_leader``: 16 Q-values, one per (leader's move, own move), row by row, instead
    of 4. ``safety``: a second head beside the dueling one, 16 logits of whether each joint move (leader's
    move, follower's move, row by row) is safe (``safety_logits``, ``teacher.safety_horizon``).
    ``safety_encoder``: that head reads an encoder of its own, a copy of the layers the Q-values read, instead
    of their features (``teacher.safety_encoder``). ``roles``: the number of agents that share the network, each
    with its role (index) as input, the Q-values ``(N, roles, outputs)``; 0: one agent, no role input, ``(N,
    outputs)``."""

    obs_shape: tuple[int, int, int]
    high: float = 255.0
    hidden: int = 128
    channels: tuple[int, int, int] = (16, 32, 32)
    window: tuple[int, int, int] | None = None
    compass: bool = False
    frame_channels: int | None = None
    cells: tuple[int, int] | None = None
    forecast: bool = False
    answers_leader: bool = False
    safety: bool = False
    safety_encoder: bool = False
    roles: int = 0

    def build(self) -> DuelingQNetwork:
        return DuelingQNetwork(self)

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "network") -> NetworkSpec:
        """The spec of a card's ``networks.<module>`` (``where``, for errors): cards of 0.1 load unchanged;
        an unknown key, or a removed option at other than its neutral value, is a one-line ``ConfigError``."""
        values = drop_removed(where, values)
        known = {f.name: f for f in dataclasses.fields(cls)}
        for key in values:
            if key not in known:
                raise ConfigError(f"{where}.{key}: unknown key; allowed: {', '.join(known)}")
        kinds = {"obs_shape": int, "channels": int, "window": int, "cells": int, "high": float, "hidden": int,
                 "frame_channels": int, "roles": int}
        out = {}
        for key, value in values.items():
            kind = kinds.get(key, bool)
            if value is None:
                out[key] = None
            elif isinstance(value, list | tuple):
                out[key] = tuple(kind(v) for v in value)
            else:
                out[key] = kind(value)
        return cls(**out)


class DuelingQNetwork(nn.Module):
    """uint8 observations -> Q-values of the four actions (or 16, ``answers_leader``), as ``spec`` says
    (``NetworkSpec``)."""

    def __init__(self, spec: NetworkSpec):
        super().__init__()
        self.spec = spec
        obs_shape, high, hidden, channels = spec.obs_shape, spec.high, spec.hidden, spec.channels
        window, frame_channels, cells, forecast = spec.window, spec.frame_channels, spec.cells, spec.forecast
        answers_leader, safety, safety_encoder = spec.answers_leader, spec.safety, spec.safety_encoder
        self.obs_shape = tuple(obs_shape)
        screens = min(obs_shape[:2]) >= 64
        frame_channels = frame_channels or (3 if screens else 4)
        self.register_buffer("scale", torch.tensor(1.0 / high), persistent=False)
        self.cells = None
        seen = self.obs_shape
        if cells is not None:
            if not screens:
                raise ValueError(f"cells: only screens are read per cell, not {self.obs_shape} observations")
            self.cells = ScreenCells(self.obs_shape, tuple(cells))
            seen = self.cells.out_shape
        self.forecast = None
        if forecast:
            if screens and self.cells is None:
                raise ValueError("forecast: screens must be read per cell (cells)")
            if seen[2] < 2 * frame_channels:
                raise ValueError(f"forecast: needs two frames or more, not {seen[2] // frame_channels}")
            self.forecast = ObstacleForecast(seen[:2], frame_channels, screens)
            seen = (*seen[:2], seen[2] + len(FORECAST_LAGS))
        self.window = None
        if spec.compass and window is None:
            raise ValueError("compass: needs a window")
        if window is not None:
            self.window = LeaderWindow(seen, tuple(window), frame_channels, screens, spec.compass)
            seen = self.window.out_shape
        self.encoder = encoder(seen, channels, screens and self.cells is None)
        with torch.no_grad():
            n = self.encoder(torch.zeros(1, seen[2], seen[0], seen[1])).shape[1]
        self.value = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        outputs = N_ACTIONS ** 2 if answers_leader else N_ACTIONS
        self.advantage = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, outputs))
        self.roles = spec.roles
        if spec.roles:
            if safety:
                raise ValueError("roles: a network with a safety head has one agent")
            # the one-hot role's weights in each head's first layer (the features' are the layer itself)
            self.value_role = nn.Linear(spec.roles, hidden, bias=False)
            self.advantage_role = nn.Linear(spec.roles, hidden, bias=False)
        self.safety = None
        if safety:
            self.safety = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, N_ACTIONS ** 2))
        self.safety_encoder = None
        if safety_encoder:
            if not safety:
                raise ValueError("safety_encoder: needs a safety head (safety)")
            # wrapped once more, as the shipped policies' weights are named (safety_encoder.0.*)
            self.safety_encoder = nn.Sequential(encoder(seen, channels, screens and self.cells is None))
        # what ``prepare`` depends on: equal keys, equal outputs for the same observations
        cells, forecast, window = self.cells, self.forecast, self.window
        self.prepare_key = (self.obs_shape, 1.0 / high,
                            None if cells is None else (tuple(cells.rows.tolist()), tuple(cells.cols.tolist())),
                            None if forecast is None else (forecast.height, forecast.width, forecast.frame_channels,
                                                           forecast.screens, tuple(forecast.lags.tolist())),
                            None if window is None else (window.out_shape, window.up, window.down, window.side,
                                                         window.frame_channels, window.screens, window.compass))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.q_values(self.prepare(obs))

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        """uint8 observations -> what the layers with weights read, ``(N, C, H, W)`` floats: the layers
        without weights (cells, forecast, window). Two networks of the same ``prepare_key`` prepare
        alike, so a learner prepares a batch once for the online and target networks of every module.
        A network with ``cells`` takes whole screens or their cells (``ScreenCells``), with the same result."""
        if self.cells is not None:
            obs = self.cells(obs)
        extra = self.forecast(obs) if self.forecast is not None else None
        if self.window is not None:
            x = self.window(obs, self.scale, extra)
        else:
            x = obs.float() * self.scale
            x = x if extra is None else torch.cat([x, extra], dim=3)
        return x.permute(0, 3, 1, 2)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """What both heads read, from ``prepare``'s output."""
        return self.encoder(x)

    def q_values(self, x: torch.Tensor) -> torch.Tensor:
        """Q-values from ``prepare``'s output."""
        return self.q_of(self.features(x))

    def q_of(self, features: torch.Tensor) -> torch.Tensor:
        """The dueling head's Q-values from ``features``: (N, outputs), or (N, roles, outputs) with ``roles``,
        each role's first layer the features' plus its one-hot code's (the layer read on both, concatenated)."""
        if not self.roles:
            return dueling(self.value(features), self.advantage(features))

        def head(layers: nn.Sequential, role: nn.Linear) -> torch.Tensor:
            hidden = layers[0](features)[:, None, :] + role.weight.T[None]  # (N, roles, hidden)
            return layers[2](layers[1](hidden))

        return dueling(head(self.value, self.value_role), head(self.advantage, self.advantage_role))


    def safety_logits(self, x: torch.Tensor, features: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 16) logits of each joint move being safe, from ``prepare``'s output (a network with ``safety``).
        The head reads its own encoder's features of ``x``, or else the Q-values' (``features``, where the
        caller has them already)."""
        if self.safety_encoder is not None:
            return self.safety(self.safety_encoder(x))
        return self.safety(self.features(x) if features is None else features)


def tied(spec: NetworkSpec, shared: DuelingQNetwork) -> DuelingQNetwork:
    """A network of ``spec`` whose layers with weights are ``shared``'s own, not copies: the same team reading
    another board (``spec.cells``; the leader's window makes every board's input alike), so that an update on
    either's batch trains both."""
    net = spec.build()
    for name, layers in shared.named_children():
        if any(True for _ in layers.parameters()):
            setattr(net, name, layers)
    return net


def outputs_of(networks: dict[str, DuelingQNetwork], obs: torch.Tensor, prepared: dict | None = None
               ) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
    """Each network's Q-values for the same observations, and the probability (N, 4, 4) its safety heads
    give each joint move (leader's move, follower's move) of being safe, their mean (None: no heads); the
    layers without weights run once for the networks that prepare alike, as in ``q_values_of``.
    ``prepared``: a dict that keeps what they gave, by ``prepare_key``, for the caller to read."""
    prepared = {} if prepared is None else prepared
    q, safe = {}, []
    for name, net in networks.items():
        if net.prepare_key not in prepared:
            prepared[net.prepare_key] = net.prepare(obs)
        x = prepared[net.prepare_key]
        features = net.features(x)
        q[name] = net.q_of(features)
        if net.safety is not None:
            safe.append(torch.sigmoid(net.safety_logits(x, features)))
    if not safe:
        return q, None
    return q, torch.stack(safe).mean(0).reshape(len(obs), N_ACTIONS, N_ACTIONS)


def q_values_of(networks: dict[str, DuelingQNetwork], obs: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each network's Q-values for the same observations, the layers without weights run once for the
    networks that prepare alike (``DuelingQNetwork.prepare_key``): the leader's and the follower's read
    the same screens."""
    prepared: dict[tuple, torch.Tensor] = {}
    out = {}
    for name, net in networks.items():
        key = net.prepare_key
        if key not in prepared:
            prepared[key] = net.prepare(obs)
        out[name] = net.q_values(prepared[key])
    return out
