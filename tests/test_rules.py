"""Each rule of ``docs/GAME.md`` on hand-built scenarios.

Setting 1 is a 25x25 board: destination (0, 12), c0 = 12 - 5 = 7, obstacle band rows [5, 20).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import formation.env as fenv
from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame

F, FL, FR, S = 0, 1, 2, 3


def make(setting=1, **overrides):
    return fenv.parallel_env(setting, **overrides)


def scen(leader, follower, obstacles=()):
    return {"leader": list(leader), "follower": list(follower), "obstacles": [list(o) for o in obstacles]}


def step_once(scenario, leader_action, follower_action, setting=1, **overrides):
    env = make(setting, **overrides)
    env.reset(options={"scenario": scenario})
    obs, rew, term, trunc, info = env.step({"leader": leader_action, "follower": follower_action})
    return env, rew, term, trunc, info


# --------------------------------------------------------------------------- moves
@pytest.mark.parametrize("action, expected", [(F, (9, 10)), (FL, (9, 9)), (FR, (9, 11)), (S, (10, 10))])
def test_each_action_moves_the_leader(action, expected):
    _, _, _, _, info = step_once(scen((10, 10), (10, 13)), action, S)
    assert tuple(info["leader"]["position"]) == expected
    assert tuple(info["follower"]["position"]) == (10, 13)


@pytest.mark.parametrize("action, expected", [(F, (11, 13)), (FL, (11, 12)), (FR, (11, 14)), (S, (12, 13))])
def test_each_action_moves_the_follower(action, expected):
    _, _, _, _, info = step_once(scen((10, 10), (12, 13)), S, action)
    assert tuple(info["follower"]["position"]) == expected
    assert tuple(info["leader"]["position"]) == (10, 10)


@pytest.mark.parametrize("action, expected", [(F, (0, 5)), (FL, (0, 4)), (FR, (0, 6)), (S, (0, 5))])
def test_row_zero_forward_stays_and_diagonals_slide(action, expected):
    _, _, _, _, info = step_once(scen((0, 5), (0, 8)), action, S)
    assert tuple(info["leader"]["position"]) == expected


def test_column_edges_clamp():
    # Leader at column 0 moving left-forward only moves up; follower at W-1 moving right-forward too.
    _, _, _, _, info = step_once(scen((10, 0), (10, 2)), FL, S)
    assert tuple(info["leader"]["position"]) == (9, 0)
    _, _, _, _, info = step_once(scen((10, 22), (10, 24)), S, FR)
    assert tuple(info["follower"]["position"]) == (9, 24)
    # A corner: (0, 0) with FL stays put.
    _, _, _, _, info = step_once(scen((0, 2), (0, 0)), S, FL)
    assert tuple(info["follower"]["position"]) == (0, 0)


def test_agents_move_at_once():
    # The follower may step into the cell the leader leaves in the same step.
    _, _, _, _, info = step_once(scen((10, 10), (11, 12)), FL, FL)
    assert tuple(info["leader"]["position"]) == (9, 9)
    assert tuple(info["follower"]["position"]) == (10, 11)


# --------------------------------------------------------------------------- obstacles
def obstacles_after(obstacles, n_steps=1):
    """Obstacles (row, col, v) after n steps with the agents parked far away."""
    env = make(1)
    leader, follower = env.config.starts
    env.reset(options={"scenario": scen(leader, follower[0], obstacles)})
    for _ in range(n_steps):
        env.step({"leader": S, "follower": S})
    return [tuple(o) for o in env.scenario()["obstacles"]]


@pytest.mark.parametrize("start, end", [
    ((5, 0, -1), (5, 1, 1)),      # at column 0 moving left: goes to 1, now moving right
    ((6, 24, 1), (6, 23, -1)),    # at W-1 moving right: goes to W-2, now moving left
    ((7, 23, 2), (7, 23, -2)),    # speed 2 bounce mid-step: 24, then back to 23
    ((8, 24, 2), (8, 22, -2)),    # speed 2 at the edge: reverse first, then two cells
    ((9, 1, -2), (9, 1, 2)),      # mirror image at column 0
    ((10, 0, -2), (10, 2, 2)),
    ((11, 12, 2), (11, 14, 2)),   # free movement
    ((12, 12, -1), (12, 11, -1)),
    ((13, 1, -1), (13, 0, -1)),   # reaching the edge does not reverse; leaving it would
])
def test_obstacle_moves_and_bounces(start, end):
    assert obstacles_after([start]) == [end]


def test_obstacle_bounces_over_several_steps():
    cols = [obstacles_after([(5, 1, -1)], n)[0][1:] for n in range(1, 5)]
    assert cols == [(0, -1), (1, 1), (2, 1), (3, 1)]
    cols = [obstacles_after([(5, 22, 2)], n)[0][1:] for n in range(1, 5)]
    assert cols == [(24, 2), (22, -2), (20, -2), (18, -2)]


def test_obstacles_never_change_row():
    obs = [(5, 0, -2), (12, 24, 1), (19, 13, -1)]
    for n in (1, 7, 30):
        assert [o[0] for o in obstacles_after(obs, n)] == [5, 12, 19]


# --------------------------------------------------------------------------- collisions
def collisions(leader, follower, obstacles, actions=(S, S)):
    _, rew, term, _, info = step_once(scen(leader, follower, obstacles), *actions)
    return info["leader"]["collided"], info["follower"]["collided"], term["leader"]


def test_touching_is_a_collision_and_diagonal_is_not():
    # Obstacle ends directly above the leader (distance exactly 1).
    assert collisions((15, 10), (15, 13), [(14, 9, 1)]) == (True, False, True)
    # Directly beside the leader on its row.
    assert collisions((15, 10), (15, 13), [(15, 7, 2)]) == (True, False, True)
    # Diagonal neighbour (distance sqrt(2)) is not a collision.
    assert collisions((15, 10), (15, 13), [(14, 12, -1)]) == (False, False, False)
    # Two rows away (distance 2) is not.
    assert collisions((15, 10), (15, 13), [(13, 9, 1)]) == (False, False, False)
    # On the very cell.
    assert collisions((15, 10), (15, 13), [(15, 11, -1)]) == (True, False, True)


def test_fast_obstacle_is_caught_by_its_intermediate_cell():
    # Speed 2 from (14, 9): sub-step 1 reaches (14, 10), right above the leader; sub-step 2
    # ends at (14, 11), only diagonal to both agents. Only the intermediate cell touches.
    assert collisions((15, 10), (15, 12), [(14, 9, 2)]) == (True, False, True)
    # Control: the same end cell reached at speed 1 from (14, 10) is no collision.
    assert collisions((15, 10), (15, 12), [(14, 10, 1)]) == (False, False, False)


def test_fast_obstacle_cannot_jump_over_an_agent():
    # Speed 6 along the agent's row ends two cells past it: every cell on the way counts.
    assert collisions((15, 10), (17, 10), [(15, 6, 6)]) == (True, False, True)
    # Control: the same end cell from the other side, without passing the agent.
    assert collisions((15, 10), (17, 10), [(15, 14, -2)]) == (False, False, False)


def test_obstacle_start_cell_does_not_count():
    # The obstacle starts right above the leader but moves away to a diagonal cell.
    assert collisions((15, 10), (15, 13), [(14, 10, -1)]) == (False, False, False)
    # The leader moves next to the obstacle's start cell, which it then leaves.
    assert collisions((16, 10), (16, 13), [(14, 10, -1)], actions=(F, F)) == (False, False, False)
    # At the edge: from column 0 moving left it goes to 1; an agent below column 0 is diagonal,
    # an agent below column 1 is touched.
    assert collisions((15, 0), (15, 2), [(14, 0, -1)]) == (False, False, False)
    assert collisions((15, 1), (15, 3), [(14, 0, -1)]) == (True, False, True)


def test_start_cell_counts_when_reached_again_by_a_bounce():
    # Speed 2 from (14, 23) moving right: reaches 24, then back to 23 (its start cell).
    # The leader at (14, 22) touches only cell 23, reached after sub-step 2.
    assert collisions((14, 22), (14, 20), [(14, 23, 2)]) == (True, False, True)
    # Without the bounce (speed 1 would end at 24) nothing touches.
    assert collisions((14, 22), (14, 20), [(14, 23, 1)]) == (False, False, False)


def test_agents_move_before_obstacles():
    # The leader steps up to (14, 10); the obstacle then reaches (14, 11), right beside it.
    assert collisions((15, 10), (15, 13), [(14, 12, -1)], actions=(F, S)) == (True, False, True)


# --------------------------------------------------------------------------- formation
def formation_after(leader, follower, config=None):
    """Formation and distance with the agents placed directly, both staying, no obstacles."""
    config = config or GameConfig.from_setting(1, n_obstacles=0)
    game = BatchedGame(config, 1)
    game.load([{"leader": [10, 10], "follower": [10, 12], "obstacles": []}])
    game.positions[0, 0] = leader
    game.positions[0, 1] = follower
    game.step(np.array([[S, S]]))
    return bool(game.formation_kept[0]), float(game.distances[0, 0]), bool(game.terminated[0])


@pytest.mark.parametrize("offset, kept", [
    ((0, 0), False), ((0, 1), False), ((1, 0), False),      # dist <= d_min = 1: broken
    ((1, 1), True), ((0, 2), True), ((2, 2), True), ((0, 3), True), ((2, 3), True),  # just inside
    ((0, 4), False), ((4, 0), False),                        # dist exactly d_max = 4: broken
    ((1, 4), False), ((3, 3), False), ((0, 5), False),
])
def test_formation_bounds(offset, kept):
    follower = (10 + offset[0], 10 + offset[1])
    got_kept, distance, terminated = formation_after((10, 10), follower)
    assert distance == pytest.approx(math.hypot(*offset))
    assert got_kept is kept
    assert terminated is (not kept)


@pytest.mark.parametrize("offset, kept", [
    ((1, 1), False), ((0, 2), True), ((2, 2), True), ((0, 3), False), ((1, 3), False),
])
def test_formation_bounds_from_config(offset, kept):
    config = GameConfig.from_setting(1, n_obstacles=0, d_min=1.5, d_max=3.0)
    got_kept, _, _ = formation_after((10, 10), (10 + offset[0], 10 + offset[1]), config)
    assert got_kept is kept


def test_formation_at_exactly_d_min_and_d_max_through_moves():
    # Follower steps to distance 1.
    _, rew, term, _, info = step_once(scen((10, 10), (12, 10)), S, F)
    assert info["follower"]["distance"] == 1.0 and not info["leader"]["formation_kept"]
    assert rew == {"leader": -1.0, "follower": -1.0} and term["leader"] and term["follower"]
    # Leader steps to distance 4.
    _, rew, term, _, info = step_once(scen((10, 10), (13, 10)), F, S)
    assert info["follower"]["distance"] == 4.0 and not info["follower"]["formation_kept"]
    assert rew == {"leader": -1.0, "follower": -1.0} and term["leader"]
    # Distance sqrt(2): kept.
    _, rew, term, _, info = step_once(scen((10, 10), (10, 12)), S, FL)
    assert info["follower"]["distance"] == pytest.approx(math.sqrt(2)) and info["leader"]["formation_kept"]
    assert rew == {"leader": 1.0, "follower": 1.0} and not term["leader"]


# --------------------------------------------------------------------------- reach, rewards, end
def test_reach_with_formation_kept_is_success():
    env, rew, term, trunc, info = step_once(scen((1, 12), (1, 10)), F, F)
    assert info["leader"]["reached"] and info["leader"]["success"] and info["follower"]["success"]
    assert rew == {"leader": 51.0, "follower": 1.0}
    assert term == {"leader": True, "follower": True} and trunc == {"leader": False, "follower": False}
    assert env.agents == []


def test_reach_by_sliding_along_row_zero():
    _, rew, term, _, info = step_once(scen((0, 11), (0, 9)), FR, FR)
    assert info["leader"]["reached"] and info["leader"]["success"]
    assert rew["leader"] == 51.0 and term["leader"]


def test_not_reached_next_to_destination():
    _, rew, term, _, info = step_once(scen((0, 13), (0, 15)), F, F)
    assert not info["leader"]["reached"] and not term["leader"] and rew["leader"] == 1.0


def test_follower_on_destination_is_not_reach():
    _, rew, term, _, info = step_once(scen((1, 10), (1, 12)), F, F)
    assert not info["leader"]["reached"] and not term["leader"] and rew == {"leader": 1.0, "follower": 1.0}


def test_reach_with_a_collision_is_not_success():
    # Obstacle arrives right below the leader's new cell (0, 12).
    _, rew, term, _, info = step_once(scen((1, 12), (1, 10), [(1, 13, -1)]), F, F)
    assert info["leader"]["reached"] and info["leader"]["collided"]
    assert not info["leader"]["success"] and not info["follower"]["success"]
    assert rew == {"leader": 50.0 - 1.0 + 1.0, "follower": 1.0}
    assert term["leader"] and term["follower"]


def test_reach_with_follower_collision_is_not_success():
    _, rew, term, _, info = step_once(scen((1, 12), (1, 10), [(0, 7, 2)]), F, F)
    assert info["leader"]["reached"] and info["follower"]["collided"] and not info["leader"]["collided"]
    assert not info["leader"]["success"]
    assert rew == {"leader": 51.0, "follower": 0.0}


def test_reach_with_broken_formation_is_not_success():
    # Follower ends at (0, 8), distance exactly 4 = d_max.
    _, rew, term, _, info = step_once(scen((1, 12), (1, 9)), F, FL)
    assert info["leader"]["reached"] and not info["leader"]["formation_kept"]
    assert not info["leader"]["success"]
    assert rew == {"leader": 49.0, "follower": -1.0} and term["leader"]


@pytest.mark.parametrize("follower, obstacle, expected", [
    ((15, 13), (14, 9, 1), {"leader": 0.0, "follower": 1.0}),    # leader collides
    ((15, 13), (14, 12, 1), {"leader": 1.0, "follower": 0.0}),   # follower collides
    ((15, 12), (15, 9, 2), {"leader": 0.0, "follower": 0.0}),    # both: (15, 11) touches both
])
def test_collision_reward_is_each_agents_own(follower, obstacle, expected):
    _, rew, term, trunc, info = step_once(scen((15, 10), follower, [obstacle]), S, S)
    assert rew == expected
    assert term == {"leader": True, "follower": True} and trunc == {"leader": False, "follower": False}
    assert not info["leader"]["success"]


def test_collision_and_broken_formation_add_up():
    # Follower steps to distance 1 from the leader, and an obstacle reaches its cell, touching both.
    _, rew, _, _, info = step_once(scen((15, 10), (17, 10), [(16, 12, -2)]), S, F)
    assert info["leader"]["collided"] and info["follower"]["collided"]
    assert rew == {"leader": -2.0, "follower": -2.0}


def test_reward_weights_from_config():
    weights = dict(reward_reach=10.0, reward_collision=-5.0, reward_formation_kept=0.25,
                   reward_formation_broken=-3.0)
    _, rew, _, _, _ = step_once(scen((1, 12), (1, 10), [(1, 13, -1)]), F, F, **weights)
    assert rew == {"leader": pytest.approx(10 - 5 + 0.25), "follower": pytest.approx(0.25)}
    _, rew, _, _, _ = step_once(scen((10, 10), (12, 10)), S, F, **weights)
    assert rew == {"leader": -3.0, "follower": -3.0}
    _, rew, _, _, _ = step_once(scen((15, 10), (15, 12), [(14, 11, 1)]), S, S, **weights)
    assert rew == {"leader": 0.25, "follower": pytest.approx(-5 + 0.25)}


def test_plain_step_keeps_going_with_formation_reward():
    _, rew, term, trunc, info = step_once(scen((20, 10), (20, 12)), F, F)
    assert rew == {"leader": 1.0, "follower": 1.0}
    assert term == {"leader": False, "follower": False} and trunc == {"leader": False, "follower": False}
    assert info["leader"]["steps"] == 1 and not info["leader"]["success"]


def test_truncation_at_max_steps():
    env = make(1, max_steps=3)
    env.reset(options={"scenario": scen((20, 10), (20, 12))})
    for t in range(1, 4):
        _, rew, term, trunc, info = env.step({"leader": S, "follower": S})
        assert term == {"leader": False, "follower": False}
        assert trunc == {"leader": t == 3, "follower": t == 3}
        assert rew == {"leader": 1.0, "follower": 1.0}
    assert env.agents == [] and not info["leader"]["success"]
    with pytest.raises(RuntimeError):
        env.step({"leader": S, "follower": S})


def test_default_episode_limit_is_200():
    env = make(1)
    env.reset(options={"scenario": scen((20, 10), (20, 12))})
    for _ in range(199):
        _, _, term, trunc, _ = env.step({"leader": S, "follower": S})
        assert not term["leader"] and not trunc["leader"]
    _, _, term, trunc, _ = env.step({"leader": S, "follower": S})
    assert trunc == {"leader": True, "follower": True} and not term["leader"]


@pytest.mark.parametrize("scenario, actions", [
    (scen((1, 12), (1, 10)), (F, F)),          # reach on the last allowed step
    (scen((10, 10), (12, 10)), (S, F)),        # formation broken on the last allowed step
    (scen((15, 10), (15, 13), [(14, 9, 1)]), (S, S)),  # collision on the last allowed step
])
def test_terminated_wins_over_truncated(scenario, actions):
    _, _, term, trunc, _ = step_once(scenario, *actions, max_steps=1)
    assert term == {"leader": True, "follower": True}
    assert trunc == {"leader": False, "follower": False}


def test_infos_have_the_spec_fields():
    env = make(1)
    _, reset_infos = env.reset(options={"scenario": scen((20, 10), (20, 13))})
    for infos in (reset_infos, env.step({"leader": F, "follower": S})[4]):
        for agent in ("leader", "follower"):
            info = infos[agent]
            assert isinstance(info["position"], list) and len(info["position"]) == 2
            assert all(isinstance(info[k], bool) for k in ("collided", "formation_kept", "reached", "success"))
            assert isinstance(info["distance"], float)
    assert infos["follower"]["distance"] == pytest.approx(math.hypot(1, 3))
    assert infos["leader"]["position"] == [19, 10]


# --------------------------------------------------------------------------- starts and n_followers
@pytest.mark.parametrize("setting", [1, 2, 3, 4])
def test_default_starts_of_the_named_settings(setting):
    env = make(setting)
    _, infos = env.reset(seed=0)
    H = W = 25 if setting <= 2 else 50
    c0 = W // 2 - W // 5
    if setting in (1, 3):
        assert infos["leader"]["position"] == [H - 1, c0] and infos["follower"]["position"] == [H - 1, c0 - 2]
    else:
        assert infos["leader"]["position"] == [H - 3, c0] and infos["follower"]["position"] == [H - 1, c0]
    assert env.config.n_obstacles == (3 if setting <= 2 else 8)
    assert env.config.destination == (0, W // 2)
    assert (env.config.d_min, env.config.d_max, env.config.max_steps) == (1, 4, 200)


@pytest.mark.parametrize("setting", [1, 2, 3, 4])
def test_two_followers_names_and_default_starts(setting):
    env = make(setting, n_followers=2)
    assert env.possible_agents == ["leader", "follower_1", "follower_2"]
    _, infos = env.reset(seed=1)
    H = W = 25 if setting <= 2 else 50
    c0 = W // 2 - W // 5
    got = [infos[a]["position"] for a in env.possible_agents]
    if setting in (1, 3):
        assert got == [[H - 1, c0], [H - 1, c0 - 2], [H - 1, c0 + 2]]
    else:
        assert got == [[H - 3, c0], [H - 1, c0 - 1], [H - 1, c0 + 1]]


def two(leader, f1, f2, obstacles=()):
    return {"leader": list(leader), "followers": [list(f1), list(f2)], "obstacles": [list(o) for o in obstacles]}


def step_two(scenario, actions, **overrides):
    env = make(1, n_followers=2, **overrides)
    env.reset(options={"scenario": scenario})
    return env.step(dict(zip(env.possible_agents, actions)))


def test_two_followers_too_close_to_each_other_break_the_formation():
    # Followers end at (12, 10) and (12, 11): 1 apart, each within (1, 4) of the leader.
    _, rew, term, _, info = step_two(two((10, 10), (13, 9), (13, 11)), (S, FR, F))
    assert info["follower_1"]["distance"] == 2.0 and info["follower_2"]["distance"] == pytest.approx(math.sqrt(5))
    assert not info["leader"]["formation_kept"]
    assert rew == {"leader": -1.0, "follower_1": -1.0, "follower_2": -1.0}
    assert all(term.values())


def test_two_followers_sqrt2_apart_keep_the_formation():
    _, rew, term, _, info = step_two(two((10, 10), (13, 9), (13, 11)), (S, FR, S))
    assert info["leader"]["formation_kept"] and not any(term.values())
    assert rew == {"leader": 1.0, "follower_1": 1.0, "follower_2": 1.0}


def test_two_followers_far_from_each_other_keep_the_formation():
    # 6 apart (> d_max) is fine between followers: only d_min applies to them.
    _, rew, term, _, info = step_two(two((10, 10), (12, 7), (12, 13)), (S, S, S))
    assert info["leader"]["formation_kept"] and not any(term.values())


def test_two_followers_one_too_far_from_the_leader():
    _, rew, term, _, info = step_two(two((10, 10), (12, 9), (13, 11)), (F, S, S))
    assert info["follower_2"]["distance"] == pytest.approx(math.hypot(4, 1))
    assert not info["leader"]["formation_kept"] and all(term.values())


def test_two_followers_each_own_collision_term():
    # An obstacle touches follower_2 only: the episode ends for all, only follower_2 pays.
    _, rew, term, trunc, info = step_two(two((10, 10), (12, 8), (12, 12), [(13, 10, 2)]), (S, S, S))
    assert [info[a]["collided"] for a in ("leader", "follower_1", "follower_2")] == [False, False, True]
    assert rew == {"leader": 1.0, "follower_1": 1.0, "follower_2": 0.0}
    assert all(term.values()) and not any(trunc.values())


def test_two_followers_leader_reach():
    _, rew, term, _, info = step_two(two((1, 12), (2, 10), (2, 14)), (F, F, F))
    assert info["leader"]["reached"] and info["leader"]["success"]
    assert rew == {"leader": 51.0, "follower_1": 1.0, "follower_2": 1.0} and all(term.values())


# --------------------------------------------------------------------------- config errors
def assert_one_line_error(excinfo, field):
    message = str(excinfo.value)
    assert "\n" not in message
    assert message.startswith(f"{field}:"), message
    return message


@pytest.mark.parametrize("call, field", [
    (lambda: GameConfig.from_setting(5), "setting"),
    (lambda: GameConfig.from_setting(0), "setting"),
    (lambda: fenv.parallel_env(7), "setting"),
    (lambda: GameConfig.from_setting(1, d_min=4.0), "d_min"),
    (lambda: GameConfig.from_setting(1, d_min=5.0, d_max=4.0), "d_min"),
    (lambda: GameConfig.from_setting(1, d_max=0.5), "d_min"),
    (lambda: GameConfig.from_setting(1, n_obstacles=16), "n_obstacles"),  # band rows 5..19: 15
    (lambda: GameConfig.from_setting(3, n_obstacles=31), "n_obstacles"),  # band rows 10..39: 30
    (lambda: GameConfig.from_setting(1, leader_start=(25, 7)), "leader_start"),
    (lambda: GameConfig.from_setting(1, leader_start=(24, -1), follower_starts=[(24, 1)]), "leader_start"),
    (lambda: GameConfig.from_setting(1, follower_starts=[(24, 25)]), "follower_starts"),
    (lambda: GameConfig.from_setting(1, follower_starts=[(24, 7)]), "follower_starts"),  # overlap
    (lambda: GameConfig.from_setting(1, follower_starts=[(24, 8)]), "follower_starts"),  # breaks formation
    (lambda: GameConfig.from_setting(1, n_followers=2, follower_starts=[(24, 5), (24, 6)]), "follower_starts"),
    (lambda: GameConfig.from_setting(1, leader_start=(0, 12), follower_starts=[(0, 10)]), "leader_start"),
    (lambda: GameConfig.from_setting(1, bogus=1), "bogus"),
    (lambda: fenv.parallel_env(1, speed=3), "speed"),
    (lambda: GameConfig.from_setting(1, formation="diagonal"), "formation"),
    (lambda: GameConfig.from_setting(1, max_steps=0), "max_steps"),
    (lambda: GameConfig.from_setting(1, obstacle_speeds=[0]), "obstacle_speeds"),
])
def test_config_errors_are_one_line_naming_the_field(call, field):
    with pytest.raises(ConfigError) as excinfo:
        call()
    assert_one_line_error(excinfo, field)


def test_config_limits_are_inclusive():
    assert GameConfig.from_setting(1, n_obstacles=15).n_obstacles == 15
    assert GameConfig.from_setting(1, d_min=1.9).d_min == 1.9
    with pytest.raises(ConfigError, match="^follower_starts:"):
        GameConfig.from_setting(1, d_min=2.0)  # the default start (distance 2) breaks it


@pytest.mark.parametrize("scenario, words", [
    (scen((20, 10), (20, 12), [(20, 10, 1)]), "overlap"),          # obstacle on the leader
    (scen((20, 10), (20, 10)), "overlap"),                          # agents on one cell
    (scen((20, 10), (20, 12), [(5, 3, 1), (5, 3, -1)]), "overlap"),
    (scen((25, 10), (24, 10)), "leader"),                           # off board
    (scen((20, 10), (20, -1)), "follower"),
    (scen((20, 10), (20, 12), [(5, 25, 1)]), "obstacles[0]"),
    (scen((20, 10), (20, 12), [(5, 3, 0)]), "obstacles[0]"),        # no velocity
    (scen((20, 10), (20, 11)), "formation"),                        # starts broken
    (scen((0, 12), (0, 10)), "destination"),
    ({**scen((20, 10), (20, 12)), "extra": 1}, "extra"),            # unknown key
    ({"leader": [20, 10], "obstacles": []}, "follower"),            # missing key
    ({"leader": [20, 10], "followers": [[20, 12]], "obstacles": []}, "followers"),
])
def test_scenario_errors_are_one_line_naming_the_field(scenario, words):
    env = make(1)
    with pytest.raises(ConfigError) as excinfo:
        env.reset(options={"scenario": scenario})
    message = assert_one_line_error(excinfo, "scenario")
    assert words in message


def test_two_follower_scenario_needs_followers_key():
    env = make(1, n_followers=2)
    with pytest.raises(ConfigError) as excinfo:
        env.reset(options={"scenario": scen((10, 10), (12, 10))})
    assert "follower" in assert_one_line_error(excinfo, "scenario")
    with pytest.raises(ConfigError) as excinfo:
        env.reset(options={"scenario": two((10, 10), (12, 9), (12, 10))})  # 1 apart: broken
    assert_one_line_error(excinfo, "scenario")


# --------------------------------------------------------------------------- seeding and random resets
@pytest.mark.parametrize("setting", [1, 4])
def test_seeded_resets_reproduce(setting):
    a, b = make(setting), make(setting)
    for seed in (0, 1, 12345):
        a.reset(seed=seed)
        b.reset(seed=seed)
        assert a.scenario() == b.scenario()
    # Unseeded resets after a seeded one continue the same stream.
    a.reset(seed=7)
    b.reset(seed=7)
    for _ in range(3):
        a.reset()
        b.reset()
        assert a.scenario() == b.scenario()


def test_different_seeds_give_different_scenarios():
    env = make(1)
    seen = []
    for seed in range(10):
        env.reset(seed=seed)
        seen.append(str(env.scenario()))
    assert len(set(seen)) == 10


def test_seeded_observations_reproduce():
    a, b = make(2), make(2)
    oa, _ = a.reset(seed=3)
    ob, _ = b.reset(seed=3)
    np.testing.assert_array_equal(oa["leader"], ob["leader"])


@pytest.mark.parametrize("setting", [1, 3])
def test_random_resets_follow_the_spec(setting):
    config = GameConfig.from_setting(setting)
    game = BatchedGame(config, batch_size=4000, seed=0)
    game.reset()
    H, W, O = config.height, config.width, config.n_obstacles
    lo, hi = H // 5, H - H // 5
    rows, cols = game.obstacle_rows, game.obstacle_cols
    assert rows.shape == (4000, O)
    assert ((rows >= lo) & (rows < hi)).all()
    assert all(len(set(r)) == O for r in rows.tolist())  # distinct rows in each game
    assert ((cols >= 0) & (cols < W)).all()
    assert set(np.unique(game.obstacle_speeds).tolist()) == {1, 2}
    assert set(np.unique(game.obstacle_dirs).tolist()) == {-1, 1}
    # Roughly uniform: every row of the band, every column, both speeds and signs are common.
    n = rows.size
    assert np.all(np.abs(np.bincount(rows.ravel() - lo, minlength=hi - lo) / n - 1 / (hi - lo)) < 0.2 / (hi - lo))
    assert np.all(np.abs(np.bincount(cols.ravel(), minlength=W) / n - 1 / W) < 0.2 / W)
    assert abs((game.obstacle_speeds == 2).mean() - 0.5) < 0.03
    assert abs((game.obstacle_dirs == 1).mean() - 0.5) < 0.03
    leader, followers = config.starts
    assert (game.positions[:, 0] == leader).all() and (game.positions[:, 1:] == followers).all()
    assert (game.steps == 0).all() and not game.done.any()


def test_random_reset_after_a_scenario_with_other_obstacle_count():
    env = make(1)
    env.reset(options={"scenario": scen((20, 10), (20, 12))})
    assert env.scenario()["obstacles"] == []
    env.reset(seed=0)
    obstacles = env.scenario()["obstacles"]
    assert len(obstacles) == 3 and len({o[0] for o in obstacles}) == 3


# --------------------------------------------------------------------------- scenario round trip
ROUND_TRIP_ACTIONS = [(F, F), (S, S), (FR, FR), (S, F), (F, S), (FL, FL), (S, S), (F, F), (S, S),
                      (FR, FR), (S, S), (S, S), (FL, FL), (S, S)]


@pytest.mark.parametrize("overrides", [dict(frame_stack=1), dict(frame_stack=4), dict(obs_type="grid", frame_stack=1),
                                       dict(n_followers=2, frame_stack=1)])
def test_scenario_round_trip(overrides):
    env = make(1, **overrides)
    agents = env.possible_agents
    if len(agents) == 2:
        start = scen((24, 7), (24, 5), [(6, 0, -2), (11, 24, 1), (15, 13, 2), (8, 3, -1)])
    else:
        start = two((23, 7), (24, 5), (24, 9), [(6, 0, -2), (11, 24, 1), (13, 13, 2)])
    env.reset(options={"scenario": start})

    def act(pair):
        return {a: (pair[0] if a == "leader" else pair[1]) for a in agents}

    for pair in ROUND_TRIP_ACTIONS[:5]:
        env.step(act(pair))
    saved = env.scenario()
    velocities = sorted(o[2] for o in saved["obstacles"])
    assert velocities != sorted(o[2] for o in start["obstacles"])  # some bounced: not trivial
    first = [env.step(act(pair)) for pair in ROUND_TRIP_ACTIONS[5:]]
    assert not any(first[-1][2].values())  # still running: the whole replay is compared

    obs0, infos0 = env.reset(options={"scenario": saved})
    assert env.scenario() == saved
    k = env.config.frame_stack
    channels = env.observation_space("leader").shape[-1] // k
    second = [env.step(act(pair)) for pair in ROUND_TRIP_ACTIONS[5:]]
    for t, (a, b) in enumerate(zip(first, second)):
        obs_a, rew_a, term_a, trunc_a, info_a = a
        obs_b, rew_b, term_b, trunc_b, info_b = b
        for agent in agents:
            if t + 1 >= k:  # the replay's frame stack has filled with its own screens
                np.testing.assert_array_equal(obs_a[agent], obs_b[agent])
            else:  # the newest screens agree; older ones are the saved moment repeated
                np.testing.assert_array_equal(obs_a[agent][..., -channels * (t + 1):],
                                              obs_b[agent][..., -channels * (t + 1):])
        assert rew_a == rew_b and term_a == term_b and trunc_a == trunc_b
        # The step counter restarts with the replay (it is not part of a scenario).
        strip = {ag: {k2: v for k2, v in info.items() if k2 != "steps"} for ag, info in info_a.items()}
        assert strip == {ag: {k2: v for k2, v in info.items() if k2 != "steps"} for ag, info in info_b.items()}
        assert info_a["leader"]["steps"] == info_b["leader"]["steps"] + 5


def test_scenario_round_trip_through_batched_game():
    config = GameConfig.from_setting(3)
    game = BatchedGame(config, batch_size=4, seed=11)
    game.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        game.step(np.full((4, 2), S))
    assert not game.done.any()
    saved = [game.scenario(i) for i in range(4)]
    copy = BatchedGame(config, batch_size=4)
    copy.load(saved)
    for _ in range(20):
        actions = rng.integers(0, 4, size=(4, 2))
        actions[:, 1] = actions[:, 0]  # same moves: the formation holds
        game.step(actions)
        copy.step(actions)
        np.testing.assert_array_equal(game.positions, copy.positions)
        np.testing.assert_array_equal(game.obstacle_cols, copy.obstacle_cols)
        np.testing.assert_array_equal(game.obstacle_dirs, copy.obstacle_dirs)
        np.testing.assert_array_equal(game.rewards, copy.rewards)
        np.testing.assert_array_equal(game.terminated, copy.terminated)


@pytest.mark.parametrize("setting", [1, 2, 3, 4])
@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_teams_of_one_to_four_followers_start_in_formation_where_docs_game_md_puts_them(setting, k):
    """docs/GAME.md, 'Teams of 1-4 followers': c0 = W // 2 - W // 5; the horizontal team beside the leader, then
    two rows behind it (the leader two rows up from three followers on); the vertical one two rows behind it, then
    beside it. No follower starts ahead of the leader."""
    config = GameConfig.from_setting(setting, n_followers=k)
    H, c0 = config.height, config.width // 2 - config.width // 5
    leader, followers = config.starts
    if config.formation == "horizontal":
        expected = {1: ((H - 1, c0), [(H - 1, c0 - 2)]), 2: ((H - 1, c0), [(H - 1, c0 - 2), (H - 1, c0 + 2)]),
                    3: ((H - 3, c0), [(H - 3, c0 - 2), (H - 3, c0 + 2), (H - 1, c0)]),
                    4: ((H - 3, c0), [(H - 3, c0 - 2), (H - 3, c0 + 2), (H - 1, c0 - 2), (H - 1, c0 + 2)])}[k]
    else:
        expected = (H - 3, c0), {1: [(H - 1, c0)], 2: [(H - 1, c0 - 1), (H - 1, c0 + 1)],
                                 3: [(H - 1, c0 - 2), (H - 1, c0), (H - 1, c0 + 2)],
                                 4: [(H - 1, c0 - 1), (H - 1, c0 + 1), (H - 3, c0 - 2), (H - 3, c0 + 2)]}[k]
    assert (leader, list(followers)) == expected
    assert all(row >= leader[0] for row, _ in followers)
    game = BatchedGame(config, batch_size=8, seed=setting)
    game.reset()
    positions = game.positions  # (games, agents, 2)
    gaps = np.sqrt(((positions[:, :, None] - positions[:, None]) ** 2).sum(-1))
    assert (config.d_min < gaps[:, 0, 1:]).all() and (gaps[:, 0, 1:] < config.d_max).all()  # each to the leader
    followers_gaps = gaps[:, 1:, 1:][:, ~np.eye(k, dtype=bool)]
    assert (followers_gaps > config.d_min).all()  # and to each other
    game.step(np.full((8, 1 + k), 3))  # all stay: the formation holds
    assert game.formation_kept.all()


def test_a_team_without_default_starts_is_refused_in_one_line():
    with pytest.raises(ConfigError, match=r"^follower_starts: no default start for n_followers=5 \(allowed: 1-4\); "
                                          r"give follower_starts$"):
        GameConfig.from_setting(1, n_followers=5)
