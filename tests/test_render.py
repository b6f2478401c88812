"""The screen, the grid planes and the frame stack (docs/GAME.md, 'Screen (observation)')."""

from __future__ import annotations

import numpy as np
import pytest

import formation.env as fenv
from formation.config import GameConfig
from formation.game import BatchedGame, GridRenderer, Observer, ScreenRenderer
from formation.game.render import cell_pixel_bounds

F, FL, FR, S = 0, 1, 2, 3
BLACK, WHITE, RED, GREEN, BLUE = (0, 0, 0), (255, 255, 255), (255, 0, 0), (0, 255, 0), (0, 0, 255)


def span(i, n):
    """GAME.md: cell i of n covers pixels [(168*i + n) // (2*n), (168*(i+1) + n) // (2*n))."""
    return (168 * i + n) // (2 * n), (168 * (i + 1) + n) // (2 * n)


def paint(config, destination, obstacles, followers, leader):
    """The expected screen, painted cell by cell in the rules' draw order."""
    img = np.zeros((84, 84, 3), np.uint8)
    H, W = config.height, config.width

    def fill(cell, colour):
        r0, r1 = span(cell[0], H)
        c0, c1 = span(cell[1], W)
        img[r0:r1, c0:c1] = colour

    fill(destination, WHITE)
    for o in obstacles:
        fill(o, RED)
    for f in followers:
        fill(f, GREEN)
    fill(leader, BLUE)
    return img


def expected_screen(game, i=0):
    s = game.scenario(i)
    return paint(game.config, game.config.destination, [o[:2] for o in s.obstacles], s.followers, s.leader)


# --------------------------------------------------------------------------- pixel bounds
@pytest.mark.parametrize("n, cells", [
    (25, {0: (0, 3), 1: (3, 7), 12: (40, 44), 23: (77, 81), 24: (81, 84)}),
    (50, {0: (0, 2), 1: (2, 3), 2: (3, 5), 25: (42, 44), 48: (81, 82), 49: (82, 84)}),
])
def test_cell_pixel_bounds_follow_the_formula(n, cells):
    bounds = cell_pixel_bounds(n)
    for i, expected in cells.items():
        assert span(i, n) == expected  # the formula, worked by hand
        assert tuple(bounds[i]) == expected
    # Cells tile the screen: no gaps, no overlaps, last ends at 84.
    assert bounds[0, 0] == 0 and bounds[-1, 1] == 84
    assert (bounds[1:, 0] == bounds[:-1, 1]).all()
    assert ((bounds[:, 1] - bounds[:, 0]) >= 1).all()


@pytest.mark.parametrize("setting, cell", [(1, (0, 0)), (1, (24, 24)), (1, (13, 6)), (3, (49, 49)),
                                           (3, (0, 49)), (3, (31, 2))])
def test_a_leader_covers_exactly_its_cell(setting, cell):
    config = GameConfig.from_setting(setting, n_obstacles=0)
    game = BatchedGame(config, 1)
    game.load([{"leader": [10, 10], "follower": [10, 12], "obstacles": []}])
    game.positions[0, 0] = cell
    game.positions[0, 1] = config.destination  # the follower out of the way (it is green anyway)
    screen = ScreenRenderer(game).render()[0]
    blue = np.all(screen == BLUE, axis=-1)
    r0, r1 = span(cell[0], config.height)
    c0, c1 = span(cell[1], config.width)
    want = np.zeros((84, 84), bool)
    want[r0:r1, c0:c1] = True
    np.testing.assert_array_equal(blue, want)


# --------------------------------------------------------------------------- colours and order
@pytest.mark.parametrize("setting", [1, 2, 3, 4])
def test_screen_colours_and_cells(setting):
    env = fenv.parallel_env(setting, frame_stack=1)
    obs, _ = env.reset(seed=setting)
    screen = obs["leader"]
    np.testing.assert_array_equal(screen, expected_screen(env.game))
    # Every colour of the rules appears, and nothing else.
    colours = {tuple(c) for c in screen.reshape(-1, 3).tolist()}
    assert colours == {BLACK, WHITE, RED, GREEN, BLUE}
    # And again after some steps (the old cells are erased).
    rng = np.random.default_rng(setting)
    for _ in range(10):
        if not env.agents:
            break
        obs, *_ = env.step({a: int(rng.integers(0, 4)) for a in env.agents})
        np.testing.assert_array_equal(obs["leader"], expected_screen(env.game))


def test_named_entities_have_their_colours():
    env = fenv.parallel_env(1, frame_stack=1)
    obs, _ = env.reset(options={"scenario": {"leader": [20, 10], "follower": [20, 12],
                                             "obstacles": [[6, 3, 1]]}})
    screen = obs["leader"]

    def at(cell):
        r0, r1 = span(cell[0], 25)
        c0, c1 = span(cell[1], 25)
        block = screen[r0:r1, c0:c1].reshape(-1, 3)
        assert (block == block[0]).all()
        return tuple(block[0].tolist())

    assert at((0, 12)) == WHITE
    assert at((6, 3)) == RED  # a reset draws the obstacles where they start
    assert at((20, 12)) == GREEN and at((20, 10)) == BLUE and at((0, 0)) == BLACK


def overlapping_game(obs_type="pixels"):
    """A game whose state puts entities on shared cells (no scenario allows it)."""
    config = GameConfig.from_setting(1, obs_type=obs_type)
    game = BatchedGame(config, 1)
    game.load([{"leader": [20, 10], "follower": [20, 12], "obstacles": [[6, 3, 1], [7, 5, 1], [0, 9, 1]]}])
    game.obstacle_cols[0] = [3, 5, 12]  # third obstacle on the destination (0, 12)
    game.obstacle_rows[0, 2] = 0
    game.positions[0, 0] = (6, 3)  # leader on obstacle 1
    game.positions[0, 1] = (7, 5)  # follower on obstacle 2
    return game


def test_draw_order_later_on_top():
    game = overlapping_game()
    renderer = ScreenRenderer(game)
    screen = renderer.render()[0].copy()
    np.testing.assert_array_equal(screen, expected_screen(game))

    def colour(cell):
        r0, _ = span(cell[0], 25)
        c0, _ = span(cell[1], 25)
        return tuple(screen[r0, c0].tolist())

    assert colour((6, 3)) == BLUE     # leader over obstacle
    assert colour((7, 5)) == GREEN    # follower over obstacle
    assert colour((0, 12)) == RED     # obstacle over destination
    # Leader over follower over destination.
    game.positions[0, 0] = (0, 12)
    game.positions[0, 1] = (0, 12)
    screen = renderer.render()[0]
    r0, r1 = span(0, 25)
    c0, c1 = span(12, 25)
    assert (screen[r0:r1, c0:c1] == BLUE).all()
    np.testing.assert_array_equal(screen, expected_screen(game))
    # Leader over follower elsewhere; the destination shows again once they leave it.
    game.positions[0, 0] = (15, 15)
    game.positions[0, 1] = (15, 15)
    game.obstacle_cols[0, 2] = 1
    screen = renderer.render()[0]
    np.testing.assert_array_equal(screen, expected_screen(game))
    assert (screen[r0:r1, c0:c1] == WHITE).all()


def test_leader_on_the_destination_after_reaching():
    env = fenv.parallel_env(1, frame_stack=1)
    env.reset(options={"scenario": {"leader": [1, 12], "follower": [1, 10], "obstacles": []}})
    obs, *_ = env.step({"leader": F, "follower": F})
    r0, r1 = span(0, 25)
    c0, c1 = span(12, 25)
    assert (obs["leader"][r0:r1, c0:c1] == BLUE).all()
    assert not (np.all(obs["leader"] == WHITE, axis=-1)).any()


def test_batched_screens_match_each_game():
    config = GameConfig.from_setting(3)
    game = BatchedGame(config, 6, seed=4)
    game.reset()
    renderer = ScreenRenderer(game)
    rng = np.random.default_rng(0)
    for _ in range(5):
        screens = renderer.render()
        for i in range(6):
            np.testing.assert_array_equal(screens[i], expected_screen(game, i))
        game.step(rng.integers(0, 4, size=(6, 2)))


# --------------------------------------------------------------------------- grid planes
def test_grid_planes():
    env = fenv.parallel_env(1, obs_type="grid", frame_stack=1)
    obs, _ = env.reset(options={"scenario": {"leader": [20, 10], "follower": [20, 12],
                                             "obstacles": [[6, 3, 1], [9, 24, -2]]}})
    grid = obs["follower"]
    assert grid.shape == (25, 25, 4) and grid.dtype == np.uint8
    planes = {name: set(map(tuple, np.argwhere(grid[..., i]).tolist()))
              for i, name in enumerate(("destination", "obstacles", "followers", "leader"))}
    assert planes == {"destination": {(0, 12)}, "obstacles": {(6, 3), (9, 24)},
                      "followers": {(20, 12)}, "leader": {(20, 10)}}
    obs, *_ = env.step({"leader": F, "follower": FL})
    grid = obs["leader"]
    assert set(map(tuple, np.argwhere(grid[..., 1]).tolist())) == {(6, 4), (9, 22)}
    assert set(map(tuple, np.argwhere(grid[..., 2]).tolist())) == {(19, 11)}
    assert set(map(tuple, np.argwhere(grid[..., 3]).tolist())) == {(19, 10)}
    assert grid.max() == 1 and grid.sum() == 5


def test_grid_planes_keep_overlaps():
    game = overlapping_game("grid")
    grid = GridRenderer(game).render()[0]
    assert grid[6, 3].tolist() == [0, 1, 0, 1]
    assert grid[7, 5].tolist() == [0, 1, 1, 0]
    assert grid[0, 12].tolist() == [1, 1, 0, 0]
    assert grid.sum() == 6


def test_grid_two_followers():
    env = fenv.parallel_env(2, obs_type="grid", frame_stack=1, n_followers=2)
    obs, _ = env.reset(seed=0)
    grid = obs["follower_2"]
    assert set(map(tuple, np.argwhere(grid[..., 2]).tolist())) == {(24, 6), (24, 8)}
    assert set(map(tuple, np.argwhere(grid[..., 3]).tolist())) == {(22, 7)}
    assert grid[..., 1].sum() == 3


# --------------------------------------------------------------------------- frame stack
@pytest.mark.parametrize("obs_type, k", [("pixels", 4), ("pixels", 2), ("grid", 4), ("grid", 3)])
def test_frame_stack_repeats_then_oldest_first(obs_type, k):
    env = fenv.parallel_env(1, obs_type=obs_type, frame_stack=k)
    single = fenv.parallel_env(1, obs_type=obs_type, frame_stack=1)
    scenario = {"leader": [24, 7], "follower": [24, 5], "obstacles": [[6, 0, -2], [11, 24, 1], [15, 13, 2]]}
    obs, _ = env.reset(options={"scenario": scenario})
    frame, _ = single.reset(options={"scenario": scenario})
    frames = [frame["leader"]]
    c = frames[0].shape[-1]
    np.testing.assert_array_equal(obs["leader"], np.concatenate([frames[0]] * k, axis=-1))
    for t in range(6):
        actions = {"leader": F if t % 2 else S, "follower": F if t % 2 else S}
        obs, *_ = env.step(actions)
        frame, *_ = single.step(actions)
        frames.append(frame["leader"])
        history = ([frames[0]] * k + frames[1:])[-k:]
        np.testing.assert_array_equal(obs["leader"], np.concatenate(history, axis=-1))
        np.testing.assert_array_equal(obs["follower"], obs["leader"])
        assert not np.array_equal(obs["leader"][..., -c:], obs["leader"][..., -2 * c:-c])  # frames differ
    # A reset starts the stack afresh.
    obs, _ = env.reset(options={"scenario": scenario})
    np.testing.assert_array_equal(obs["leader"], np.concatenate([frames[0]] * k, axis=-1))


def paint_grid(game, i=0):
    """The expected grid planes, from the rules' entity kinds."""
    s = game.scenario(i)
    grid = np.zeros((game.config.height, game.config.width, 4), np.uint8)
    grid[(*game.config.destination, 0)] = 1
    for r, c, _ in s.obstacles:
        grid[r, c, 1] = 1
    for r, c in s.followers:
        grid[r, c, 2] = 1
    grid[(*s.leader, 3)] = 1
    return grid


@pytest.mark.parametrize("obs_type, k", [("pixels", 4), ("grid", 3)])
def test_batched_stack_with_masked_resets_matches_painted_frames(obs_type, k):
    config = GameConfig.from_setting(2, obs_type=obs_type, frame_stack=k)
    game = BatchedGame(config, 4, seed=2)
    source = BatchedGame(config, 4, seed=3)  # fresh scenarios for the games that end
    game.reset()
    observer = Observer(game)
    draw = expected_screen if obs_type == "pixels" else paint_grid
    stack = observer.observe(reset=np.ones(4, bool))
    history = [[draw(game, i)] * k for i in range(4)]
    rng = np.random.default_rng(1)
    ends = 0
    for _ in range(60):
        game.step(rng.integers(0, 4, size=(4, 2)))
        done = game.done.copy()
        if done.any():
            ends += int(done.sum())
            source.reset()
            game.load([source.scenario(i) for i in np.flatnonzero(done)], mask=done)
        stack = observer.observe(reset=done)
        for i in range(4):
            frame = draw(game, i)
            history[i] = [frame] * k if done[i] else [*history[i][1:], frame]
            np.testing.assert_array_equal(stack[i], np.concatenate(history[i], axis=-1))
    assert ends >= 4


def test_observer_batch_reset_mask():
    config = GameConfig.from_setting(1, frame_stack=2)
    game = BatchedGame(config, 2, seed=0)
    game.reset()
    observer = Observer(game)
    first = observer.observe(reset=np.array([True, True])).copy()
    np.testing.assert_array_equal(first[..., :3], first[..., 3:])
    game.step(np.full((2, 2), S))
    second = observer.observe().copy()
    np.testing.assert_array_equal(second[..., :3], first[..., 3:])
    assert not np.array_equal(second[..., :3], second[..., 3:])  # the obstacles moved


# --------------------------------------------------------------------------- dtypes and shapes
@pytest.mark.parametrize("setting, obs_type, k, shape", [
    (1, "pixels", 4, (84, 84, 12)), (3, "pixels", 4, (84, 84, 12)), (2, "pixels", 1, (84, 84, 3)),
    (1, "grid", 4, (25, 25, 16)), (4, "grid", 2, (50, 50, 8)), (3, "grid", 1, (50, 50, 4)),
])
def test_observation_dtype_and_shape(setting, obs_type, k, shape):
    env = fenv.parallel_env(setting, obs_type=obs_type, frame_stack=k, n_followers=2 if setting == 4 else 1)
    obs, _ = env.reset(seed=0)
    for agent in env.possible_agents:
        space = env.observation_space(agent)
        assert space.shape == shape and space.dtype == np.uint8
        assert obs[agent].shape == shape and obs[agent].dtype == np.uint8
        assert space.contains(obs[agent])
        assert space.high.max() == (255 if obs_type == "pixels" else 1)
    obs, *_ = env.step({a: S for a in env.agents})
    assert all(o.shape == shape and o.dtype == np.uint8 for o in obs.values())


def test_default_observation_is_four_stacked_screens():
    env = fenv.parallel_env(1)
    assert env.observation_space("leader").shape == (84, 84, 12)


def test_render_and_screen_match_the_observation():
    env = fenv.parallel_env(1, render_mode="rgb_array", frame_stack=4)
    obs, _ = env.reset(seed=5)
    np.testing.assert_array_equal(env.render(), obs["leader"][..., -3:])
    obs, *_ = env.step({"leader": F, "follower": F})
    np.testing.assert_array_equal(env.render(), obs["leader"][..., -3:])
    assert env.render().dtype == np.uint8 and env.render().shape == (84, 84, 3)
    grid_env = fenv.parallel_env(1, obs_type="grid")
    grid_env.reset(seed=5)
    np.testing.assert_array_equal(grid_env.screen(), expected_screen(grid_env.game))
    assert fenv.parallel_env(1).render() is None
