"""What the agents see: the 84x84 RGB screen, a lossless grid of entity planes, and frame stacks.

Both renderers draw the whole batch by scattering only the cells of entities (and erasing the
cells drawn last time), so a step touches a few hundred bytes per game instead of the screen.
"""

from __future__ import annotations

import numpy as np

from formation.config import GameConfig
from formation.game.core import BatchedGame

BLACK = (0, 0, 0)
WHITE = (255, 255, 255)  # destination
RED = (255, 0, 0)  # obstacles
GREEN = (0, 255, 0)  # followers
BLUE = (0, 0, 255)  # leader

# Grid planes, in the screen's draw order.
GRID_PLANES = ("destination", "obstacles", "followers", "leader")


def cell_pixel_bounds(n_cells: int, screen: int = 84) -> np.ndarray:
    """Pixel ``[start, end)`` of each cell along one axis: ``(2*screen*i + n) // (2*n)``."""
    i = np.arange(n_cells + 1)
    edges = (2 * screen * i + n_cells) // (2 * n_cells)
    return np.stack([edges[:-1], edges[1:]], axis=1)


def cell_pixels(n_cells: int, screen: int = 84) -> np.ndarray:
    """The pixel read for each cell along one axis, its first (``cell_pixel_bounds``): the renderer paints
    a whole cell in one colour, so that pixel holds all the cell shows. The networks' ``ScreenCells`` and
    the rollouts that store cells instead of screens (``GameRollout``) read the same pixels through this."""
    return cell_pixel_bounds(n_cells, screen)[:, 0]


class _EntityCells:
    """Flat cell index of every entity of every game, in draw order: destination, obstacles,
    followers, leader."""

    def __init__(self, game: BatchedGame):
        self.game = game
        self.width = game.config.width
        self._dest_cell = game.config.destination[0] * self.width + game.config.destination[1]
        self._groups: list[slice] = []
        self.cells = np.zeros(0, np.intp)

    def update(self) -> np.ndarray:
        g = self.game
        B, O, A = g.batch_size, g.n_obstacles, g.n_agents
        if self.cells.shape != (B, 1 + O + A):
            self.cells = np.zeros((B, 1 + O + A), np.intp)
            self._groups = [slice(0, 1), slice(1, 1 + O), slice(1 + O, O + A), slice(O + A, O + A + 1)]
        c = self.cells
        c[:, 0] = self._dest_cell
        np.multiply(g.obstacle_rows, self.width, out=c[:, 1:1 + O])
        c[:, 1:1 + O] += g.obstacle_cols
        # Followers then the leader, so that the leader is drawn last (on top).
        np.multiply(g.positions[:, ::-1, 0], self.width, out=c[:, 1 + O:])
        c[:, 1 + O:] += g.positions[:, ::-1, 1]
        return c

    @property
    def groups(self) -> list[slice]:
        return self._groups


class ScreenRenderer:
    """Draws the 84x84x3 uint8 screens of a whole batch (docs/GAME.md, 'Screen (observation)')."""

    def __init__(self, game: BatchedGame):
        cfg: GameConfig = game.config
        self.game = game
        S = cfg.screen_size
        self.pixels_per_screen = S * S
        rows = cell_pixel_bounds(cfg.height, S)
        cols = cell_pixel_bounds(cfg.width, S)
        # For each cell, the flat indices of its pixels, padded by repeating the first one.
        pixels = []
        for r0, r1 in rows:
            for c0, c1 in cols:
                rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
                pixels.append((rr * S + cc).ravel())
        width = max(len(p) for p in pixels)
        self._cell_pixels = np.array([np.pad(p, (0, width - len(p)), mode="edge") for p in pixels])
        self._entities = _EntityCells(game)
        self._colours = [np.array(c, np.uint8) for c in (WHITE, RED, GREEN, BLUE)]
        self.screens = np.zeros((game.batch_size, S, S, 3), np.uint8)
        self.frames = self.screens  # the common name of the last rendered batch
        self._drawn = np.zeros(0, np.intp)
        self.drawn_rows = self._drawn  # flat pixel indices (over B*84*84) drawn by the last render
        self._offsets = (np.arange(game.batch_size) * self.pixels_per_screen)[:, None, None]

    def render(self) -> np.ndarray:
        """The screens of the present state, (B, 84, 84, 3); the buffer is reused by the next call."""
        flat = self.screens.reshape(-1, 3)
        flat[self._drawn] = 0
        cells = self._entities.update()
        pix = self._cell_pixels[cells]
        pix += self._offsets
        for group, colour in zip(self._entities.groups, self._colours):
            flat[pix[:, group].ravel()] = colour
        self._drawn = pix.ravel()
        self.drawn_rows = self._drawn
        return self.screens


class GridRenderer:
    """Lossless cell-level observation: (B, H, W, 4) uint8 planes of 0/1 (``GRID_PLANES``)."""

    def __init__(self, game: BatchedGame):
        cfg = game.config
        self.game = game
        self.grids = np.zeros((game.batch_size, cfg.height, cfg.width, len(GRID_PLANES)), np.uint8)
        self.frames = self.grids  # the common name of the last rendered batch
        self._entities = _EntityCells(game)
        self._drawn = np.zeros(0, np.intp)
        n_planes = len(GRID_PLANES)
        self._cells_per_game = cfg.height * cfg.width
        self._n_planes = n_planes
        self.drawn_rows = np.zeros(0, np.intp)  # flat cell indices (over B*H*W) drawn by the last render

    def render(self) -> np.ndarray:
        flat = self.grids.reshape(-1)
        flat[self._drawn] = 0
        cells = self._entities.update()
        g = self.game
        B, O, A = g.batch_size, g.n_obstacles, g.n_agents
        plane = np.empty(cells.shape[1], np.intp)
        plane[0], plane[1:1 + O], plane[1 + O:O + A], plane[-1] = 0, 1, 2, 3
        rows = cells + (np.arange(B) * self._cells_per_game)[:, None]
        self.drawn_rows = rows.ravel()
        idx = rows * self._n_planes + plane
        self._drawn = idx.ravel()
        flat[self._drawn] = 1
        return self.grids


class FrameStack:
    """The last k frames of each game along the channel axis, oldest first.

    At a reset the stack is the first frame repeated (docs/GAME.md, 'Screen (observation)'). Two
    frames differ only where either of them has an entity drawn, so each push copies just those rows
    (the renderer's ``drawn_rows``) from one slot to the next instead of shifting whole screens.
    """

    def __init__(self, batch_size: int, frame_shape: tuple[int, ...], k: int):
        h, w, c = frame_shape
        self.k, self.c = k, c
        self.stacks = np.zeros((batch_size, h, w, c * k), np.uint8)
        self._rows = self.stacks.reshape(batch_size * h * w, c * k)
        self._history: list[np.ndarray] = []  # drawn rows of the frame in each slot, oldest first

    def push(self, frames: np.ndarray, drawn_rows: np.ndarray, reset: np.ndarray | None = None) -> np.ndarray:
        c, k, rows = self.c, self.k, self._rows
        if len(self._history) < k:
            self._history = [drawn_rows] * k
            self.stacks[:] = np.tile(frames, (1, 1, 1, k))
            return self.stacks
        new = frames.reshape(rows.shape[0], c)
        hist = self._history
        for j in range(k - 1):
            idx = np.concatenate([hist[j], hist[j + 1]])
            rows[idx, c * j:c * (j + 1)] = rows[idx, c * (j + 1):c * (j + 2)]
        idx = np.concatenate([hist[-1], drawn_rows])
        rows[idx, c * (k - 1):] = new[idx]
        self._history = [*hist[1:], drawn_rows]
        if reset is not None and reset.any():
            self.stacks[reset] = np.tile(frames[reset], (1, 1, 1, k))
        return self.stacks


class Observer:
    """The observation of the config (``obs_type``, ``frame_stack``) for a whole batch."""

    def __init__(self, game: BatchedGame):
        cfg = game.config
        self.renderer = ScreenRenderer(game) if cfg.obs_type == "pixels" else GridRenderer(game)
        frame = self.renderer.render()
        self.frame_shape = frame.shape[1:]
        self.stack = FrameStack(game.batch_size, self.frame_shape, cfg.frame_stack) if cfg.frame_stack > 1 else None
        self.shape = (*self.frame_shape[:2], self.frame_shape[2] * cfg.frame_stack)
        self.high = 255 if cfg.obs_type == "pixels" else 1

    def observe(self, reset: np.ndarray | None = None) -> np.ndarray:
        """Render the present state; ``reset`` marks games whose stack starts afresh."""
        frames = self.renderer.render()
        if self.stack is None:
            return frames
        return self.stack.push(frames, self.renderer.drawn_rows, reset)
