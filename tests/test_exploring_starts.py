"""Exploring starts (``train.exploring_starts``): training episodes that start with the team moved, in
its start formation, to a random clear place on the board; what the agents see is that state's screen."""

import numpy as np
import pytest

from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame, Observer
from formation.recipe.config import RunConfig
from formation.recipe.rollout import GameRollout, exploring_start


def spec_start(config):
    game = BatchedGame(config, batch_size=1)
    game.reset(seed=0)
    return game.scenario(0)


@pytest.mark.parametrize("setting", [1, 2, 3, 4])
def test_an_exploring_start_moves_the_team_as_one_to_a_clear_place_anywhere(setting):
    config = GameConfig.from_setting(setting)
    rng = np.random.default_rng(setting)
    game = BatchedGame(config, batch_size=1)
    leaders = []  # each start's team
    for seed in range(300):
        game.reset(seed=seed)
        scenario = game.scenario(0)
        moved = exploring_start(scenario, config, rng)
        assert moved.obstacles == scenario.obstacles
        offset = np.subtract(moved.leader, scenario.leader)
        for before, after in zip(scenario.followers, moved.followers):  # the formation as it started
            assert tuple(np.add(before, offset)) == after
        for r, c in [moved.leader, *moved.followers]:
            assert 0 <= r < config.height and 0 <= c < config.width
            assert all((r - orow) ** 2 + (c - ocol) ** 2 > 1 for orow, ocol, _ in moved.obstacles)
        assert moved.leader != config.destination
        leaders.append([moved.leader, *moved.followers])
        game.load([moved])  # a valid scenario, and not lost or won at once
        assert not game.done[0]
    teams = np.array(leaders)  # (starts, agents, 2)
    top, bottom = teams[..., 0].min(1), teams[..., 0].max(1)
    left, right = teams[..., 1].min(1), teams[..., 1].max(1)
    # anywhere: at the top row (the end game beside the destination) as well as the bottom one, either side
    assert top.min() == 0 and bottom.max() == config.height - 1
    assert left.min() == 0 and right.max() == config.width - 1


def test_a_start_with_no_clear_place_stays_where_it_was():
    config = GameConfig.from_setting(None, height=9, width=9, n_obstacles=1)
    scenario = spec_start(config)
    rng = np.random.default_rng(0)
    assert exploring_start(scenario, config, rng, tries=0) == scenario


@pytest.mark.parametrize("obs_type", ["pixels", "grid"])
def test_rollouts_start_that_share_of_episodes_from_exploring_starts_and_show_their_screens(obs_type):
    config = GameConfig.from_setting(2, obs_type=obs_type, frame_stack=2)
    spec = BatchedGame(config, batch_size=64, seed=5)
    spec.reset()
    at_spec = {spec.scenario(i).leader for i in range(64)}
    assert len(at_spec) == 1  # the spec starts every team at one place
    never = GameRollout(config, 64, seed=5)
    assert {never.game.scenario(i).leader for i in range(64)} == at_spec
    rollout = GameRollout(config, 64, seed=5, exploring_starts=0.5)
    moved = [rollout.game.scenario(i).leader not in at_spec for i in range(64)]
    assert 16 <= sum(moved) <= 48
    rng = np.random.default_rng(0)
    restarts = moved_restarts = 0
    started = {i: "exploring" if moved[i] else "spec" for i in range(64)}  # where each game's episode started
    for _ in range(40):
        rollout.step(rng.integers(0, 4, (64, 2)))
        restarted = np.flatnonzero(rollout.game.steps == 0)
        for i, episode in zip(restarted.tolist(), rollout.pop_episodes()):  # its statistics say so
            assert episode["start"] == started[i]
            started[i] = "exploring" if rollout.game.scenario(i).leader not in at_spec else "spec"
        restarts += len(restarted)
        moved_restarts += sum(rollout.game.scenario(i).leader not in at_spec for i in restarted)
        # what the agents see is the state they are in: the first stacks of a fresh render of the same states
        fresh = BatchedGame(config, batch_size=64)
        fresh.load([rollout.game.scenario(i) for i in range(64)])
        first_stacks = Observer(fresh).observe(np.ones(64, bool))
        np.testing.assert_array_equal(rollout.observations[restarted], first_stacks[restarted])
    assert restarts > 100 and 0.3 < moved_restarts / restarts < 0.7


def test_exploring_starts_must_be_a_fraction():
    with pytest.raises(ConfigError, match=r"^train\.exploring_starts: 2 is not allowed; allowed: a number in "
                                          r"\[0\.0, 1\.0\]$"):
        RunConfig.load("configs/setting4.yaml", {"train.exploring_starts": 2})
    assert RunConfig.load("configs/setting4.yaml", {"train.exploring_starts": 0.25}).train.exploring_starts == 0.25
