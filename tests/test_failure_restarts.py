"""Failure restarts (``train.failure_restarts``): training episodes that start from the state a few steps
before the end of an earlier training episode that ended in a collision or a formation break."""

import numpy as np
import pytest

from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame, Observer
from formation.learn.config import RunConfig
from formation.learn.rollout import FAILURE_STEPS_BACK, GameRollout

LOW, HIGH = FAILURE_STEPS_BACK


def play(rollout: GameRollout, steps: int, seed: int = 0, actions=None):
    """Play ``steps`` random (or the given) joint actions; after each, yield the games it restarted, the
    states 2..8 steps before the end of every episode that failed so far (restarts included) and the
    statistics of the episodes that ended (one per restarted game, in the same order)."""
    rng = np.random.default_rng(seed)
    n = rollout.batch_size
    history: list[list] = [[rollout.game.scenario(i)] for i in range(n)]  # each game's states this episode
    candidates: set = set()
    for _ in range(steps):
        joint = rng.integers(0, 4, (n, rollout.n_agents)) if actions is None else actions
        rollout.step(joint)
        restarted = np.flatnonzero(rollout.game.steps == 0)
        episodes = rollout.pop_episodes()  # one per restarted game, in the same order
        assert len(episodes) == len(restarted)
        for i, episode in zip(restarted.tolist(), episodes):
            if not episode["success"] and not episode["truncated"]:  # history[i][-1]: 1 step before the end
                candidates.update(history[i][-HIGH:len(history[i]) - LOW + 1])
        yield restarted, set(candidates), episodes
        for i in range(n):
            history[i] = [rollout.game.scenario(i)] if i in restarted else history[i] + [rollout.game.scenario(i)]


def test_failures_restart_from_a_state_two_to_eight_steps_before_their_end_and_show_its_screen():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2)
    rollout = GameRollout(config, 1, seed=3, failure_restarts=1.0)
    from_failures = 0
    expected_start = "spec"
    for restarted, candidates, episodes in play(rollout, 400):
        for i, episode in zip(restarted.tolist(), episodes):
            assert episode["start"] == expected_start  # the statistics say where the episode started
            scenario = rollout.game.scenario(i)
            expected_start = "failure" if candidates else "spec"
            if candidates:  # every restart after a failure was seen comes from one
                assert scenario in candidates
                from_failures += 1
                fresh = BatchedGame(config, batch_size=1)
                fresh.load([scenario])
                np.testing.assert_array_equal(rollout.observations[i], Observer(fresh).observe(np.ones(1, bool))[0])
    assert from_failures >= 10


def test_that_share_of_restarts_come_from_failures():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2)
    rollout = GameRollout(config, 32, seed=4, failure_restarts=0.5)
    spec = BatchedGame(config, batch_size=1)
    spec.reset(seed=0)
    spec_place = spec.scenario(0).leader
    restarts = from_failures = 0
    for step, (restarted, _, _) in enumerate(play(rollout, 200)):
        if step < 40:  # until the pool has failures in it
            continue
        for i in restarted.tolist():
            restarts += 1
            from_failures += rollout.game.scenario(i).leader != spec_place  # a mid-episode state, not a spec start
    assert restarts > 200 and 0.35 < from_failures / restarts < 0.65


def test_time_outs_and_successes_are_not_restarted_from():
    # no obstacles and a team that stands still: every episode times out
    config = GameConfig.from_setting(None, height=9, width=9, n_obstacles=0, max_steps=4, obs_type="grid",
                                     frame_stack=2)
    rollout = GameRollout(config, 8, seed=0, failure_restarts=1.0)
    start = rollout.game.scenario(0)
    stand = np.full((8, 2), 3)
    restarts = 0
    for restarted, _, episodes in play(rollout, 20, actions=stand):
        restarts += len(restarted)
        assert all(e["truncated"] and e["start"] == "spec" for e in episodes)
        assert all(rollout.game.scenario(i) == start for i in restarted)
    assert restarts == 8 * 5
    assert not rollout._failures


def test_without_failure_restarts_a_rollout_plays_as_before():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2)
    rng = np.random.default_rng(0)
    plain, off = GameRollout(config, 16, seed=7), GameRollout(config, 16, seed=7, failure_restarts=0.0)
    for _ in range(60):
        joint = rng.integers(0, 4, (16, 2))
        a, b = plain.step(joint), off.step(joint)
        np.testing.assert_array_equal(a.frames, b.frames)


def test_failure_restarts_must_be_a_fraction_and_reach_the_rollout_actors(rollout_actor):
    with pytest.raises(ConfigError, match=r"^train\.failure_restarts: 1\.5 is not allowed; allowed: a number in "
                                          r"\[0\.0, 1\.0\]$"):
        RunConfig.load("configs/setting2.yaml", {"train.failure_restarts": 1.5})

    assert rollout_actor({"train.failure_restarts": 0.25}).rollout.failure_restarts == 0.25
