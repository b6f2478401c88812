"""Greedy evaluation: the watch hook sees every step that is played, with the actions played."""

import numpy as np

from formation.config import GameConfig
from formation.evaluate import play_greedy

SMALL = GameConfig.from_setting(None, height=9, width=9, n_obstacles=1, obs_type="grid", frame_stack=2)


def test_watch_sees_each_live_step_before_it_is_played():
    rng = np.random.default_rng(0)
    seen_steps = np.zeros(20, np.int64)

    def watch(game, actions, live):
        assert not game.done[live].any()  # the step is not played yet
        assert (actions[~live] == 3).all()  # finished games stand still
        assert (game.steps[live] == seen_steps[live]).all()  # one call per step, in order
        seen_steps[live] += 1

    played = play_greedy(SMALL, lambda obs: rng.integers(0, 4, size=(len(obs), 2)), 20, seed=5, watch=watch)
    assert (seen_steps == played["steps"]).all() and seen_steps.min() >= 1


def test_a_team_of_three_followers_is_evaluated_against_the_planners_lower_bound():
    from formation.evaluate import evaluate_policy, format_report

    config = GameConfig.from_setting(1, n_followers=3, obs_type="grid", frame_stack=1)
    report = evaluate_policy(config, lambda obs: np.zeros((len(obs), 4), np.int64), 8, 0)
    p = report["planner"]
    assert p["planner_exact"] is False and set(p["best_return_mean"].values()) == {None}
    assert p["planner_solved"] == 8 and p["planner_steps_mean"] >= config.starts[0][0]  # the leader's rows to go
    text = format_report(report)
    assert "at least" in text and "a lower bound (each follower alone with the leader)" in text
