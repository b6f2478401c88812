"""The Q-network and the DQN arithmetic, in plain torch (the RLlib module and learner wrap these).

Observations arrive as uint8 ``(N, H, W, C)`` (C = frame channels x stack) and are normalised
here. The encoders are sized for CPUs: the pixel encoder's first layer reads non-overlapping
4x4 patches, so a forward pass costs about 2.4 MMAC per sample instead of the Nature DQN's 10.

With a ``LeaderWindow`` the network first shifts every frame of the stack so that the leader sits
at a fixed place and keeps a window around it (the board's edge marked by a plane of its own):
what is near the leader then lands on the same inputs wherever the team is, and a rule learnt in
one place holds in every other (docs/TRAINING.md measures what that is worth).

With a ``ScreenCells`` reader the network first takes one pixel per cell of the board from each
screen (the renderer paints a whole cell in one colour, so nothing on the screen is lost) and
reads the result as a grid, at one entry per cell: on settings 3-4 a cell is 1.68 pixels wide,
and 4x4 patches would mix two or three cells.
"""

from __future__ import annotations

import torch
from torch import nn

from formation.game.render import cell_pixel_bounds

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
    return value + advantage - advantage.mean(dim=1, keepdim=True)


def double_q_target(returns: torch.Tensor, discounts: torch.Tensor, q_next_online: torch.Tensor,
                    q_next_target: torch.Tensor) -> torch.Tensor:
    """y = R + gamma^n * Q_target(s', argmax_a Q_online(s', a))   (double DQN, van Hasselt et al. 2016).

    ``returns`` is the n-step discounted reward sum and ``discounts`` gamma^n, or 0 where the
    episode terminated within the n steps."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return returns + discounts * q_next_target.gather(1, best).squeeze(1)


def large_margin(q: torch.Tensor, labels: torch.Tensor, gap: float) -> torch.Tensor:
    """DQfD's J_E(Q) = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), l = ``gap`` for a != a_E, 0 for a_E
    (Hester et al. 2018, eq. 2), per row; ``labels`` are the teacher's actions a_E (all >= 0)."""
    a_e = labels.long().unsqueeze(1)
    margins = torch.full_like(q, gap).scatter(1, a_e, 0.0)
    return (q + margins).max(1).values - q.gather(1, a_e).squeeze(1)


class LeaderWindow(nn.Module):
    """``(N, H, W, C)`` frame stacks -> ``(N, up + 1 + down, 2 * side + 1, C + 1)``: every frame shifted
    so that the leader's top-left entry in the newest frame sits at row ``up``, column ``side``;
    entries outside the board are 0, and the extra last plane is 1 on the board.

    The leader is found in the newest frame (the last ``frame_channels`` channels): on a grid its
    own plane (the frame's last), on a screen (or its cells) its colour, pure blue (drawn last, so never hidden).
    """

    def __init__(self, obs_shape: tuple[int, int, int], window: tuple[int, int, int], frame_channels: int,
                 screens: bool):
        super().__init__()
        self.h, self.w, self.c = obs_shape
        self.up, self.down, self.side = window
        self.frame_channels, self.screens = frame_channels, screens
        self.out_shape = (self.up + 1 + self.down, 2 * self.side + 1, self.c + 1)
        # window row i is board row (leader's row - up + i); column j, board column (leader's - side + j)
        self.register_buffer("rows", torch.arange(self.out_shape[0]), persistent=False)
        self.register_buffer("cols", torch.arange(self.out_shape[1]), persistent=False)

    def leader_mask(self, obs: torch.Tensor) -> torch.Tensor:
        """(N, H, W) bool: the leader's entries in the newest frame of uint8 observations."""
        newest = obs[..., -self.frame_channels:]
        if not self.screens:
            return newest[..., -1] > 0  # GRID_PLANES: destination, obstacles, followers, leader
        red, green, blue = newest[..., 0], newest[..., 1], newest[..., 2]
        return (blue > 127) & (red < 128) & (green < 128)

    def forward(self, obs: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
        """uint8 observations -> the window as floats: the observation's entries times ``scale``, and the
        board plane (1 on the board, 0 off it) last."""
        n, h, w, c = obs.shape
        where = self.leader_mask(obs).reshape(n, -1).float().argmax(1)  # row-major: the top-left entry
        rows = (where // w)[:, None] - self.up + self.rows  # (n, window rows): rows of the board
        cols = (where % w)[:, None] - self.side + self.cols
        board = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
        flat = rows.clamp(0, h - 1)[:, :, None] * w + cols.clamp(0, w - 1)[:, None, :]
        crop = obs.reshape(n, h * w, c).gather(1, flat.reshape(n, -1, 1).expand(-1, -1, c))
        crop = crop.reshape(n, *self.out_shape[:2], c).float() * (board[..., None] * scale)
        return torch.cat([crop, board[..., None].float()], dim=3)


class ScreenCells(nn.Module):
    """``(N, S, S, C)`` screens -> ``(N, height, width, C)``: the top-left pixel of every cell of a
    ``height`` x ``width`` board, where the screen's cells start (``cell_pixel_bounds``, spec 'Screen')."""

    def __init__(self, obs_shape: tuple[int, int, int], board: tuple[int, int]):
        super().__init__()
        h, w, c = obs_shape
        height, width = board
        if height > h or width > w:
            raise ValueError(f"a {height}x{width} board has cells under one pixel on a {h}x{w} screen")
        self.out_shape = (height, width, c)
        self.register_buffer("rows", torch.as_tensor(cell_pixel_bounds(height, h)[:, 0]), persistent=False)
        self.register_buffer("cols", torch.as_tensor(cell_pixel_bounds(width, w)[:, 0]), persistent=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return obs.index_select(1, self.rows).index_select(2, self.cols)


class DuelingQNetwork(nn.Module):
    """uint8 observations -> Q-values of the four actions.

    ``window`` (rows above, rows below, columns either side of the leader, in entries of the
    observation): look through a ``LeaderWindow`` first; None: the whole observation as it is.
    ``frame_channels``: channels of one frame of the stack (3 for screens, 4 for grids).
    ``cells`` (board height, width), screens only: read one pixel per cell first (``ScreenCells``);
    ``window`` is then in cells, and the encoder's first layer reads every cell."""

    def __init__(self, obs_shape: tuple[int, int, int], high: float = 255.0, hidden: int = 128,
                 channels: tuple[int, int, int] = (16, 32, 32), window: tuple[int, int, int] | None = None,
                 frame_channels: int | None = None, cells: tuple[int, int] | None = None):
        super().__init__()
        self.obs_shape = tuple(obs_shape)
        screens = min(obs_shape[:2]) >= 64
        self.register_buffer("scale", torch.tensor(1.0 / high), persistent=False)
        self.cells = None
        seen = self.obs_shape
        if cells is not None:
            if not screens:
                raise ValueError(f"cells: only screens are read per cell, not {self.obs_shape} observations")
            self.cells = ScreenCells(self.obs_shape, tuple(cells))
            seen = self.cells.out_shape
        self.window = None
        if window is not None:
            frame_channels = frame_channels or (3 if screens else 4)
            self.window = LeaderWindow(seen, tuple(window), frame_channels, screens)
            seen = self.window.out_shape
        self.encoder = encoder(seen, channels, screens and self.cells is None)
        with torch.no_grad():
            n = self.encoder(torch.zeros(1, seen[2], seen[0], seen[1])).shape[1]
        self.value = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, N_ACTIONS))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if self.cells is not None:
            obs = self.cells(obs)
        x = obs.float() * self.scale if self.window is None else self.window(obs, self.scale)
        x = self.encoder(x.permute(0, 3, 1, 2))
        return dueling(self.value(x), self.advantage(x))
