"""Learning, for real: `formation train configs/small.yaml` (the default recipe on a 9x9 board)
reaches a greedy success rate that a random policy cannot, within a few minutes on 2 cores."""

import json

import numpy as np
import pytest

from formation.evaluate import play_greedy
from formation.recipe.config import RunConfig

SMALL = "configs/small.yaml"
pytest.importorskip("ray")


def test_a_random_policy_almost_never_succeeds_on_the_small_board():
    run = RunConfig.load(SMALL)
    rng = np.random.default_rng(0)
    agents = 1 + run.game.n_followers
    played = play_greedy(run.game, lambda obs: rng.integers(0, 4, size=(len(obs), agents)), 1000, run.eval.seed)
    summary = played["summary"]
    assert summary["success"] < 0.05, summary["success"]


def test_the_default_recipe_learns_the_small_board(tmp_path, cli):
    """Under 2 min alone on 2 cores. Measured 89.0% and 91.0% at 8k env steps (seeds 0, 1; docs/lab/TRAINING.md)."""
    out = tmp_path / "small"
    done = cli("train", SMALL, "--out", str(out))
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((out / "result.json").read_text())
    greedy = result["greedy"]
    assert result["env_steps"] >= 8_000
    assert greedy["episodes"] == 200
    # the issue asks for 80%; a random policy succeeds in under 5% (above); the recipe measured 89.0-91.0%
    assert greedy["success"] >= 0.8, greedy
    # successes take close to the shortest path (8 steps from the start row on a 9x9 board)
    assert greedy["steps_success_mean"] < 10, greedy
