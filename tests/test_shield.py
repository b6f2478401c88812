"""The safety shield: it reads the game's state off the screens exactly (the velocities as the game
moves its obstacles), its safe moves are exactly those a brute force over the game finds, it keeps the
networks' move where that is safe, and behind it a shipped policy fails less."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from formation.config import ConfigError, GameConfig
from formation.evaluate import play_greedy
from formation.game import BatchedGame, Observer
from formation.planner import (
    _Board,
    _first_moves_surviving,
    _lockstep_survivors,
    _ObstacleFuture,
    surviving_first_moves_many,
)
from formation.policy import load
from formation.shield import Shield, obstacle_readings, read_states, shielded_moves

REPO = Path(__file__).resolve().parent.parent
JOINTS = list(itertools.product(range(4), repeat=2))


def future_columns(config: GameConfig, row: int, col: int, velocity: int, steps: int = 12) -> list[int]:
    """An obstacle's columns over the next steps, as the game moves it (agents far away)."""
    game = BatchedGame(config)
    game.reset()
    h = config.height
    game.load([{"leader": [h - 3, 0], "follower": [h - 1, 0], "obstacles": [[row, col, velocity]]}])
    cols = []
    for _ in range(steps):
        game.step(np.array([[3, 3]]))
        cols.append(int(game.obstacle_cols[0, 0]))
    return cols


@pytest.mark.parametrize("width", [25, 50, 3])
def test_a_velocity_read_from_two_columns_moves_the_obstacle_as_the_game_does(width):
    config = GameConfig.from_setting(2, width=width, n_obstacles=1)
    for col, velocity in itertools.product(range(width), (-2, -1, 1, 2)):
        truth = future_columns(config, 10, col, velocity)
        readings = obstacle_readings(truth[0], col, width, (1, 2))
        assert readings, (col, velocity)
        futures = [future_columns(config, 10, truth[0], v)[:-1] for v in readings]
        assert truth[1:] in futures, (col, velocity, readings)
    # unknown before: every speed, both ways (one way at a wall)
    assert sorted(obstacle_readings(width // 2, None, width, (1, 2))) == [-2, -1, 1, 2]
    assert sorted(obstacle_readings(0, None, width, (1, 2))) == [1, 2]


@pytest.mark.parametrize("obs_type", ["pixels", "grid"])
@pytest.mark.parametrize("setting", [2, 3])
def test_the_state_read_off_the_screens_plays_out_as_the_game(setting, obs_type):
    config = GameConfig.from_setting(setting, obs_type=obs_type)
    game = BatchedGame(config, batch_size=6, seed=setting)
    game.reset()
    observer = Observer(game)
    obs = observer.observe(np.ones(6, bool))
    first = [read_states(o, config, horizon=200) for o in obs]
    # the first screen, repeated in the stack, shows no motion: every velocity of every obstacle (on
    # setting 3, 4 ** 8 readings: too many, no veto), or only of those the team can come near in one step
    if setting == 2:
        at_wall = (game.obstacle_cols == 0) | (game.obstacle_cols == config.width - 1)  # one way there
        assert [len(r) for r in first] == np.prod(np.where(at_wall, 2, 4), axis=1).tolist()
    else:
        assert all(r is None for r in first)
    near = [read_states(o, config, horizon=1) for o in obs]
    assert all(len(r) == 1 for r in near)  # obstacles start 3 rows or more above the team: one reading
    rng = np.random.default_rng(0)
    for _ in range(3):
        game.step(rng.choice([0, 3], size=(6, 2)))
        live = ~game.done
        obs = observer.observe(np.zeros(6, bool))
        for i in np.flatnonzero(live):
            readings = read_states(obs[i], config, horizon=200)
            truth = game.scenario(i).to_dict()
            assert readings is not None and len(readings) == 1  # one velocity fits each obstacle's motion
            reading = readings[0]
            assert reading["leader"] == truth["leader"] and reading["follower"] == truth["follower"]
            got = sorted(reading["obstacles"])
            want = sorted(truth["obstacles"])
            assert [o[:2] for o in got] == [o[:2] for o in want]
            for (row, col, v), (_, _, true_v) in zip(got, want):
                assert future_columns(config, row, col, v) == future_columns(config, row, col, true_v)


def fails_within(config: GameConfig, scenario: dict, sequences: np.ndarray) -> np.ndarray:
    """For each sequence of joint moves (N, steps, 2) played from ``scenario``: whether its game ends unsuccessfully
    within it. One game per sequence, all played at once; a game's outcome is read at the step it ends."""
    game = BatchedGame(config, batch_size=len(sequences))
    game.reset()
    game.load([scenario] * len(sequences))
    ended, failed = np.zeros(len(sequences), bool), np.zeros(len(sequences), bool)
    for t in range(sequences.shape[1]):
        game.step(sequences[:, t])
        failed |= game.done & ~ended & ~game.success
        ended |= game.done
    return failed


def test_surviving_first_moves_are_exactly_those_with_a_safe_continuation():
    config = GameConfig.from_setting(2, height=9, width=9, n_obstacles=3, max_steps=40)
    game = BatchedGame(config, batch_size=20, seed=5)
    game.reset()
    rng = np.random.default_rng(1)
    for _ in range(3):  # mid-episode states, obstacles near the team
        game.step(rng.choice([0, 3], size=(20, 2), p=[0.7, 0.3]))
        game.reset(mask=game.done)
    scenarios = [game.scenario(i).to_dict() for i in range(20)]
    horizon = 3
    masks = surviving_first_moves_many(scenarios, config=config, horizon=horizon)
    seen_unsafe = 0
    sequences = np.array(list(itertools.product(JOINTS, repeat=horizon)))  # first joint move slowest
    for scenario, mask in zip(scenarios, masks):
        failed = fails_within(config, scenario, sequences).reshape(len(JOINTS), -1)
        for k, joint in enumerate(JOINTS):
            safe = not failed[k].all()
            assert safe == bool((int(mask) >> k) & 1), (scenario, joint)
            seen_unsafe += not safe
    assert seen_unsafe > 20  # the states tested had moves to veto


def test_a_move_into_an_obstacle_is_vetoed_and_a_safe_greedy_move_is_kept():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2)
    game = BatchedGame(config)
    game.reset()
    # an obstacle in the row ahead of the leader, coming its way: (14, 13) moving left, at (14, 12) after a step
    game.load([{"leader": [15, 10], "follower": [17, 10], "obstacles": [[14, 13, -1], [5, 0, 1], [6, 24, -1]]}])
    observer = Observer(game)
    observer.observe(np.ones(1, bool))
    game.step(np.array([[3, 3]]))
    obs = observer.observe(np.zeros(1, bool))
    allowed = Shield(config, horizon=1).allowed(obs)[0]
    assert not allowed[0].any() and not allowed[2].any()  # forward, forward-right: next to the obstacle
    assert allowed[3, 3] and not allowed[3, 0]  # both stay; the follower may not close up on a standing leader
    assert allowed[1, 0] and allowed[1, 1]  # forward-left passes
    leader_q = np.array([[9.0, 1.0, 2.0, 0.0]])
    follower_q = np.tile(np.array([5.0, 1.0, 1.0, 0.0]), (1, 4, 1))
    assert shielded_moves(leader_q, follower_q, allowed[None]).tolist() == [[1, 0]]
    everything = np.ones((1, 4, 4), bool)
    assert shielded_moves(leader_q, follower_q, everything).tolist() == [[0, 0]]  # greedy when all are safe


def test_the_follower_changes_its_answer_before_the_leader_changes_its_move():
    leader_q = np.array([[5.0, 4.0, 3.0, 2.0]])
    follower_q = np.tile(np.array([9.0, 8.0, 7.0, 6.0]), (1, 4, 1))
    allowed = np.zeros((1, 4, 4), bool)
    allowed[0, 0, 2] = allowed[0, 1, 0] = True
    assert shielded_moves(leader_q, follower_q, allowed).tolist() == [[0, 2]]
    allowed[0, 0, 2] = False
    assert shielded_moves(leader_q, follower_q, allowed).tolist() == [[1, 0]]
    assert shielded_moves(leader_q, follower_q, np.zeros((1, 4, 4), bool)).tolist() == [[0, 0]]


def test_a_bad_horizon_or_several_followers_is_one_line():
    with pytest.raises(ConfigError, match=r"shield: 0 is not allowed; allowed: an integer >= 1"):
        Shield(GameConfig.from_setting(1), 0)
    with pytest.raises(ConfigError, match=r"shield: n_followers 2 is not allowed; allowed: 1"):
        Shield(GameConfig.from_setting(1, n_followers=2), 3)


def test_a_shipped_policy_behind_the_shield_fails_less_and_acts_alike_through_pettingzoo():
    policy = load(REPO / "policies" / "setting2")
    shielded = policy.shielded(4)
    assert policy.shield is None  # the policy itself is unchanged
    alone = play_greedy(policy.game, policy.act_batch, 100, 2_000_000)
    behind = play_greedy(policy.game, shielded.act_batch, 100, 2_000_000)
    assert behind["success"].sum() >= alone["success"].sum()
    assert behind["summary"]["success"] >= 0.97, behind["summary"]
    assert not (alone["success"] & ~behind["success"]).any()  # no game the networks win is lost behind it
    from formation.env import parallel_env
    env = parallel_env(**shielded.env_config)
    obs, _ = env.reset(seed=2_000_000)
    for _ in range(5):
        joint = shielded.act_batch(obs["leader"][None])[0]
        actions = shielded.act(obs)
        assert [actions["leader"], actions["follower"]] == joint.tolist()
        obs, *_ = env.step(actions)


def test_evaluate_behind_the_shield_reports_it_and_a_bad_horizon_is_one_line(tmp_path, capfd):
    from formation.cli import main
    out = tmp_path / "shielded.json"
    folder = str(REPO / "policies" / "setting1")
    assert main(["evaluate", folder, "--episodes", "20", "--workers", "1", "--shield", "3", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["shield"] == 3 and report["episodes"] == 20 and report["success"] > 0.5
    assert "behind a shield of 3 steps" in capfd.readouterr().out
    assert main(["evaluate", folder, "--shield", "-2"]) == 2
    out_text, err = capfd.readouterr()
    assert "Traceback" not in out_text + err
    assert err.strip().splitlines() == ["formation: error: --shield: -2 is not allowed; allowed: an integer >= 0 "
                                        "(steps ahead; 0: none)"]


def test_a_finished_or_unreadable_game_gets_no_veto():
    config = GameConfig.from_setting(2)
    game = BatchedGame(config, batch_size=2)
    game.reset()
    game.load([{"leader": [15, 10], "follower": [17, 10], "obstacles": [[5, 3, 1], [6, 20, -1], [7, 12, 2]]}] * 2)
    observer = Observer(game)
    observer.observe(np.ones(2, bool))
    game.step(np.array([[0, 3], [0, 0]]))  # the first game's leader walks away: distance 3, still kept
    game.step(np.array([[0, 3], [0, 0]]))  # distance 4: broken, the game is over
    assert game.done.tolist() == [True, False]
    obs = observer.observe(np.zeros(2, bool))
    shield = Shield(config, horizon=2)
    allowed = shield.allowed(obs)
    assert allowed[0].all() and not allowed[1].all()  # the live game keeps its vetoes
    blank = np.zeros_like(obs[:1])  # no agent on the screen
    assert shield.allowed(blank).all()


@pytest.mark.parametrize("setting", [2, 3])
def test_first_moves_shown_safe_by_lockstep_continuations_need_no_search_and_change_nothing(setting):
    config = GameConfig.from_setting(setting)
    game = BatchedGame(config, batch_size=400, seed=7)
    game.reset()
    rng = np.random.default_rng(2)
    scenarios = []
    for _ in range(12):  # states all over the board, near obstacles, some near the destination
        moves = np.where(rng.random((400, 1)) < 0.7, 0, rng.integers(0, 4, (400, 1)))
        game.step(np.repeat(moves, 2, axis=1))
        game.reset(mask=game.done)
        scenarios += [game.scenario(i) for i in range(0, 400, 40)]
    for horizon in (1, 2, 6):
        steps = np.full(len(scenarios), horizon)
        searched = _first_moves_surviving(scenarios, config, steps, shortcut=False)
        assert np.array_equal(_first_moves_surviving(scenarios, config, steps), searched)
        assert np.array_equal(surviving_first_moves_many(scenarios, config=config, horizon=horizon), searched)
    # the continuations alone find most safe first moves, and only safe ones
    board = _Board(config)
    zones = _ObstacleFuture(config, scenarios, board).zones(6)
    starts = np.array([[r * board.width + c for r, c in (s.leader, *s.followers)] for s in scenarios], np.int32)
    shown = _lockstep_survivors(board, zones, starts, np.full(len(scenarios), 6))
    assert ((shown & ~searched) == 0).all()
    assert ones(shown) > 0.8 * ones(searched) and ones(searched) < 16 * len(scenarios)


def ones(masks: np.ndarray) -> int:
    """Set bits over all of ``masks``."""
    return sum(bin(int(m)).count("1") for m in masks)
