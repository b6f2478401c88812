"""The sparse frame stack equals a plain stack of independently rendered frames, resets included."""

import numpy as np
import pytest

from formation.config import GameConfig
from formation.game import BatchedGame, GridRenderer, Observer, ScreenRenderer


@pytest.mark.parametrize("obs_type", ["pixels", "grid"])
@pytest.mark.parametrize("k", [2, 4])
def test_sparse_stack_matches_rendered_frames(obs_type, k):
    config = GameConfig.from_setting(1, obs_type=obs_type, frame_stack=k)
    game = BatchedGame(config, batch_size=8, seed=1)
    game.reset()
    observer = Observer(game)
    reference = (ScreenRenderer if obs_type == "pixels" else GridRenderer)(game)
    observer.observe(np.ones(8, bool))
    frame = reference.render().copy()
    history = [frame] * k
    rng = np.random.default_rng(0)
    resets = 0
    for _ in range(300):
        game.step(rng.integers(0, 4, (8, 2)))
        done = game.done.copy()
        resets += done.sum()
        if done.any():
            game.reset(mask=done)
        stack = observer.observe(done)
        frame = reference.render().copy()
        history = [*history[1:], frame]
        history = [np.where(done[:, None, None, None], frame, h) for h in history]
        np.testing.assert_array_equal(stack, np.concatenate(history, axis=-1))
    assert resets > 10  # the check covered episode boundaries
