"""Property tests: random boards, scenarios and action sequences against the rules (docs/GAME.md)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import formation.env as fenv
from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame

PROPERTY_SETTINGS = settings(max_examples=150, deadline=None,
                             suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


@st.composite
def configs(draw):
    """A named setting, or a small board, with one or two followers and a short episode limit."""
    n_followers = draw(st.sampled_from([1, 2]))
    max_steps = draw(st.integers(1, 40))
    if draw(st.booleans()):
        setting = draw(st.sampled_from([1, 2, 3, 4]))
        return GameConfig.from_setting(setting, n_followers=n_followers, max_steps=max_steps)
    height = draw(st.integers(6, 14))
    width = draw(st.integers(7, 14))
    formation = draw(st.sampled_from(["horizontal", "vertical"]))
    band = height - 2 * (height // 5)
    n_obstacles = draw(st.integers(0, band))
    try:
        return GameConfig.from_setting(None, height=height, width=width, n_obstacles=n_obstacles,
                                       formation=formation, n_followers=n_followers, max_steps=max_steps)
    except ConfigError:
        assume(False)


@st.composite
def scenarios(draw, config):
    """Default starts and hand-drawn obstacles anywhere off the agents, speeds 1..3 either way."""
    leader, followers = config.starts
    taken = {tuple(leader), *map(tuple, followers)}
    cells = st.tuples(st.integers(0, config.height - 1), st.integers(0, config.width - 1))
    obstacle_cells = draw(st.lists(cells.filter(lambda c: c not in taken), max_size=6, unique=True))
    velocities = st.integers(1, 3).flatmap(lambda s: st.sampled_from([s, -s]))
    obstacles = [[r, c, draw(velocities)] for r, c in obstacle_cells]
    out = {"leader": list(leader), "obstacles": obstacles}
    if config.n_followers == 1:
        out["follower"] = list(followers[0])
    else:
        out["followers"] = [list(f) for f in followers]
    return out


def joint_actions(n_agents):
    # Mostly the same move for everyone (episodes then last), sometimes independent moves.
    same = st.integers(0, 3).map(lambda a: (a,) * n_agents)
    mixed = st.tuples(*[st.integers(0, 3)] * n_agents)
    return st.lists(st.one_of(same, same, mixed), min_size=1, max_size=60)


def check_invariants(game, config, rows0, speeds0):
    H, W = config.height, config.width
    pos = game.positions
    assert ((pos[..., 0] >= 0) & (pos[..., 0] < H) & (pos[..., 1] >= 0) & (pos[..., 1] < W)).all()
    np.testing.assert_array_equal(game.obstacle_rows, rows0)
    assert ((game.obstacle_cols >= 0) & (game.obstacle_cols <= W - 1)).all()
    np.testing.assert_array_equal(game.obstacle_speeds, speeds0)
    assert set(np.unique(game.obstacle_dirs).tolist()) <= {-1, 1}


@PROPERTY_SETTINGS
@given(data=st.data())
def test_hand_drawn_scenarios_follow_the_rules(data, reference):
    config = data.draw(configs())
    scenario = data.draw(scenarios(config))
    game = BatchedGame(config, 1)
    game.load([scenario])
    actions = data.draw(joint_actions(game.n_agents))
    positions = [tuple(p) for p in game.positions[0].tolist()]
    obstacles = [tuple(o) for o in game.scenario(0).obstacles]
    rows0, speeds0 = game.obstacle_rows.copy(), game.obstacle_speeds.copy()
    for t, joint in enumerate(actions):
        want = reference(config, positions, obstacles, joint, t)
        game.step(np.array([joint]))
        check_invariants(game, config, rows0, speeds0)
        assert [tuple(p) for p in game.positions[0].tolist()] == want.positions
        assert [tuple(o) for o in game.scenario(0).obstacles] == want.obstacles
        assert game.collided[0].tolist() == want.collided
        assert bool(game.formation_kept[0]) == want.formation_kept
        assert bool(game.reached[0]) == want.reached
        np.testing.assert_allclose(game.rewards[0], want.rewards, rtol=1e-6)
        assert bool(game.terminated[0]) == want.terminated
        assert bool(game.truncated[0]) == want.truncated
        assert bool(game.success[0]) == want.success
        # The episode ends exactly when the rules say, and never runs past max_steps.
        assert bool(game.done[0]) == (want.terminated or t + 1 >= config.max_steps)
        assert int(game.steps[0]) == t + 1 <= config.max_steps
        if game.done[0]:
            break
        positions, obstacles = want.positions, want.obstacles


@PROPERTY_SETTINGS
@given(config=configs(), seed=st.integers(0, 2**32 - 1), data=st.data())
def test_random_resets_then_random_play_follow_the_rules(config, seed, data, reference):
    B = 4
    game = BatchedGame(config, B, seed=seed)
    game.reset()
    rows0, speeds0 = game.obstacle_rows.copy(), game.obstacle_speeds.copy()
    lo, hi = config.obstacle_band
    assert ((rows0 >= lo) & (rows0 < hi)).all()
    assert all(len(set(r)) == config.n_obstacles for r in rows0.tolist())
    assert set(np.unique(speeds0).tolist()) <= {1, 2}
    states = [game.scenario(i) for i in range(B)]
    live = np.ones(B, bool)
    moves = data.draw(st.lists(st.lists(st.integers(0, 3), min_size=B * game.n_agents,
                                        max_size=B * game.n_agents), min_size=1, max_size=40))
    for t, flat in enumerate(moves):
        joint = np.array(flat).reshape(B, game.n_agents)
        game.step(joint)
        check_invariants(game, config, rows0, speeds0)
        for i in np.flatnonzero(live):
            s = states[i]
            want = reference(config, [s.leader, *s.followers], list(s.obstacles), joint[i].tolist(), t)
            assert [tuple(p) for p in game.positions[i].tolist()] == want.positions
            assert [tuple(o) for o in game.scenario(i).obstacles] == want.obstacles
            assert bool(game.terminated[i]) == want.terminated
            assert bool(game.truncated[i]) == want.truncated
            assert bool(game.success[i]) == want.success
            np.testing.assert_allclose(game.rewards[i], want.rewards, rtol=1e-6)
            states[i] = game.scenario(i)
        live &= ~game.done
        if not live.any():
            break


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), setting=st.sampled_from([1, 2, 3, 4]),
       actions=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 3)), min_size=1, max_size=50))
def test_env_episode_ends_exactly_when_the_spec_says(seed, setting, actions):
    env = fenv.parallel_env(setting, max_steps=30, frame_stack=1)
    env.reset(seed=seed)
    for t, (a, b) in enumerate(actions):
        before = env.scenario()
        _, rew, term, trunc, info = env.step({"leader": a, "follower": b})
        ends = (info["leader"]["reached"] or info["leader"]["collided"] or info["follower"]["collided"]
                or not info["leader"]["formation_kept"])
        assert term == {"leader": ends, "follower": ends}
        assert trunc == {"leader": (not ends) and t + 1 == 30, "follower": (not ends) and t + 1 == 30}
        assert info["leader"]["success"] == (info["leader"]["reached"] and info["leader"]["formation_kept"]
                                              and not info["leader"]["collided"]
                                              and not info["follower"]["collided"])
        after = env.scenario()
        assert [o[0] for o in after["obstacles"]] == [o[0] for o in before["obstacles"]]
        assert [abs(o[2]) for o in after["obstacles"]] == [abs(o[2]) for o in before["obstacles"]]
        if ends or t + 1 == 30:
            assert env.agents == []
            break
        assert env.agents == ["leader", "follower"]


@pytest.mark.parametrize("setting", [1, 3])
def test_scenario_reading_is_loadable_while_running(setting):
    # Every state reached before the end of an episode is a valid scenario (no overlaps, formation kept).
    env = fenv.parallel_env(setting, frame_stack=1)
    other = fenv.parallel_env(setting, frame_stack=1)
    rng = np.random.default_rng(setting)
    checked = 0
    for seed in range(5):
        env.reset(seed=seed)
        while env.agents:
            a = int(rng.integers(0, 4))
            env.step({"leader": a, "follower": a if rng.random() < 0.8 else int(rng.integers(0, 4))})
            if env.agents:
                saved = env.scenario()
                other.reset(options={"scenario": saved})
                assert other.scenario() == saved
                checked += 1
    assert checked >= 10
