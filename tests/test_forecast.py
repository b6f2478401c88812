"""The obstacle forecast layer against the game's own rule of motion (formation.game.core)."""

import numpy as np
import pytest
import torch

from formation.env import parallel_env
from formation.game import BatchedGame
from formation.recipe.qnet import FORECAST_LAGS, NetworkSpec, ObstacleForecast, ScreenCells


def true_danger(env, leader_row: int, lags=FORECAST_LAGS) -> np.ndarray:
    """(H, W, lags) bool from the game itself: after s steps, the cells within distance 1 of a cell some
    obstacle reached on step s, for s = max(leader_row - row + lag, 1) on each row."""
    cfg = env.config
    game = BatchedGame(cfg, 1)
    game.load([env.scenario()])
    horizon = leader_row + max(lags) + 2
    reached = []  # per step: (row, col) cells the obstacles reached
    for _ in range(horizon):
        cells = [np.stack([game.obstacle_rows[0], cols[0].copy()], 1) for cols in game.sweep_obstacles()]
        reached.append(np.concatenate(cells))
    out = np.zeros((cfg.height, cfg.width, len(lags)), bool)
    for j, lag in enumerate(lags):
        for row in range(cfg.height):
            step = max(leader_row - row + lag, 1)
            for r, c in reached[step - 1]:
                for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
                    if r + dr == row and 0 <= c + dc < cfg.width:
                        out[row, c + dc, j] = True
    return out


def forecast_of(env, obs: np.ndarray, grid: bool) -> np.ndarray:
    cfg = env.config
    x = torch.from_numpy(obs[None])
    if not grid:
        x = ScreenCells(obs.shape, (cfg.height, cfg.width))(x)
    layer = ObstacleForecast((cfg.height, cfg.width), 4 if grid else 3, screens=not grid)
    return layer(x)[0].numpy() > 0


@pytest.mark.parametrize("setting,obs_type", [(1, "grid"), (3, "grid"), (2, "pixels"), (4, "pixels")])
def test_forecast_equals_the_games_future_once_obstacles_moved(setting, obs_type):
    env = parallel_env(setting, obs_type=obs_type, frame_stack=2)
    rng = np.random.default_rng(setting)
    checked = 0
    for seed in range(12):
        obs, _ = env.reset(seed=seed)
        for t in range(12):
            move = int(rng.integers(4))  # the same move for both keeps the formation
            actions = {a: move for a in env.agents}
            obs, _, term, trunc, infos = env.step(actions)
            if any(term.values()) or any(trunc.values()):
                break
            leader_row = infos["leader"]["position"][0]
            expected = true_danger(env, leader_row)
            got = forecast_of(env, obs["leader"], obs_type == "grid")
            assert np.array_equal(got, expected), (seed, t)
            checked += 1
    assert checked > 40


def test_a_bounce_that_leaves_an_obstacle_in_place_is_read_as_one():
    # at column 1 moving left at speed 2: to 0, then it turns and comes back to 1 (same column on both screens)
    env = parallel_env(1, obs_type="grid", frame_stack=2)
    scenario = {"leader": [24, 7], "follower": [24, 5], "obstacles": [[10, 1, -2], [14, 20, 1], [18, 5, -1]]}
    env.reset(options={"scenario": scenario})
    obs, *_ = env.step({"leader": 3, "follower": 3})
    assert env.scenario()["obstacles"][0][1] == 1
    assert np.array_equal(forecast_of(env, obs["leader"], True), true_danger(env, 24))


def test_first_screen_marks_every_speed_and_direction():
    env = parallel_env(3, obs_type="grid", frame_stack=2)
    for seed in range(5):
        obs, infos = env.reset(seed=seed)
        got = forecast_of(env, obs["leader"], True)
        expected = true_danger(env, infos["leader"]["position"][0])
        assert not (expected & ~got).any()  # the true future is always marked
        assert (got & ~expected).any()  # and more, as the velocities are unknown


def test_network_with_forecast_reads_grids_and_cells_and_refuses_patches():
    for shape, cells, high in (((25, 25, 8), None, 1), ((84, 84, 12), (50, 50), 255)):
        for window in (None, (12, 3, 10)):
            net = NetworkSpec(shape, high, window=window, cells=cells, forecast=True).build()
            obs = torch.randint(0, high + 1, (3, *shape), dtype=torch.uint8)
            assert net(obs).shape == (3, 4)
    with pytest.raises(ValueError, match="per cell"):
        NetworkSpec((84, 84, 12), forecast=True).build()
    with pytest.raises(ValueError, match="two frames"):
        NetworkSpec((25, 25, 4), 1, forecast=True).build()
