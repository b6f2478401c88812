"""The frame replay: stacks built at sample time equal what the env produced, each screen is
stored once (only its cells, where the networks read screens per cell), n-step returns equal a hand
computation, prioritized sampling follows priorities."""

import numpy as np
import pytest
import torch

from formation.config import GameConfig
from formation.recipe.qnet import ScreenCells
from formation.recipe.replay import Chunk, FrameReplay, SumTree
from formation.recipe.rollout import GameRollout, concatenate


def play(config, batch, steps, capacity, seed=0, n_agents=2, screen_cells=False):
    """Random play into a replay; returns (replay, {record id: the stack the agents saw})."""
    rollout = GameRollout(config, batch, seed=seed, screen_cells=screen_cells)
    replay = FrameReplay(capacity, rollout.frame_shape, n_agents, config.frame_stack, seed=seed)
    seen = {}
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        observations = rollout.observations.copy()
        chunk = rollout.step(rng.integers(0, 4, (batch, n_agents)))
        ids = replay.added + np.arange(len(chunk))
        for j in range(batch):  # the first `batch` records are this step's, in game order
            seen[int(ids[j])] = observations[j]
        replay.add(chunk)
    return replay, seen, rollout


def cells_of(screens: np.ndarray, config) -> np.ndarray:
    """What the networks read of screens (or stacks of them), by their own layer."""
    reader = ScreenCells(screens.shape[1:], (config.height, config.width))
    return reader(torch.from_numpy(np.ascontiguousarray(screens))).numpy()


@pytest.mark.parametrize("obs_type, screen_cells", [("pixels", False), ("grid", False), ("pixels", True)])
def test_sampled_stacks_equal_what_the_agents_saw(obs_type, screen_cells):
    """Where the replay stores cells, its stacks are the cells of the stacks the agents saw."""
    config = GameConfig.from_setting(1, obs_type=obs_type, frame_stack=4)
    # capacity far below what is played: the ring wraps many times
    replay, seen, _ = play(config, batch=4, steps=400, capacity=500, screen_cells=screen_cells)
    assert replay.added > 3 * replay.capacity
    if screen_cells:
        assert replay.frames.shape[1:] == (25, 25, 3)
        seen = {i: cells_of(obs[None], config)[0] for i, obs in seen.items()}
    batch = replay.sample(256, n_step=1, gamma=0.9)
    assert len(batch["ids"]) == 256
    for i, obs in zip(batch["ids"], batch["obs"]):
        np.testing.assert_array_equal(obs, seen[int(i)])
    # the next observation of a non-terminal step is what the agents saw next
    nxt = [(i, o) for i, o, d in zip(batch["ids"], batch["next_obs"], batch["discounts"]) if d > 0]
    assert nxt
    for i, obs in nxt:
        successor = replay.next[int(i) % replay.capacity]
        if int(successor) in seen:  # a truncation's successor is a terminal record, not an agent step
            np.testing.assert_array_equal(obs, seen[int(successor)])


@pytest.mark.parametrize("setting", [1, 3])
def test_a_rollout_that_reads_cells_records_the_cells_of_the_screens_it_rendered(setting):
    """Every record's frame is ``ScreenCells`` of the screen the renderer drew: a step's records of the screens
    shown before the step, a truncated episode's terminal record of the screen after its last step (a rollout
    of the same games that keeps whole screens recorded it). The agents still act on whole screens."""
    config = GameConfig.from_setting(setting, obs_type="pixels", frame_stack=2, max_steps=6)
    games = 5
    cells, whole = (GameRollout(config, games, seed=3, screen_cells=on) for on in (True, False))
    assert cells.frame_shape == (config.height, config.width, 3) and whole.frame_shape == (84, 84, 3)
    rng = np.random.default_rng(0)
    terminals = 0
    for _ in range(20):
        shown = cells.observer.renderer.screens.copy()  # what the renderer drew for the present state
        np.testing.assert_array_equal(cells.observations, whole.observations)
        assert cells.observations.shape == (games, 84, 84, 6)  # acting reads whole screens
        actions = np.repeat(rng.integers(0, 4, (games, 1)), 2, axis=1)  # as one: the formation holds
        chunk, reference = cells.step(actions), whole.step(actions)
        assert chunk.frames.shape == (len(reference), config.height, config.width, 3)
        np.testing.assert_array_equal(chunk.frames[:games], cells_of(shown, config))
        np.testing.assert_array_equal(chunk.frames, cells_of(reference.frames, config))
        np.testing.assert_array_equal(chunk.terminal, reference.terminal)
        terminals += int(chunk.terminal.sum())
    assert terminals > 0  # truncations happened: their terminal records were checked too
    with pytest.raises(ValueError, match="screen_cells"):
        GameRollout(GameConfig.from_setting(1, obs_type="grid"), 2, screen_cells=True)


def test_episode_boundaries_repeat_the_first_frame():
    config = GameConfig.from_setting(1, obs_type="grid", frame_stack=3)
    replay, seen, _ = play(config, batch=2, steps=60, capacity=10_000)
    firsts = [i for i in seen if replay.prev[i] == i]
    assert len(firsts) > 2  # several episodes started
    for i in firsts:
        stack, ok = replay.stack(np.array([i]))
        assert ok[0]
        frames = np.split(stack[0], 3, axis=-1)
        np.testing.assert_array_equal(frames[0], frames[2])
        np.testing.assert_array_equal(frames[1], frames[2])


def test_each_screen_is_stored_once():
    config = GameConfig.from_setting(1, obs_type="pixels", frame_stack=4)
    replay, seen, rollout = play(config, batch=3, steps=50, capacity=100_000)
    steps = 3 * 50
    truncated = int(replay.truncated[: replay.size].sum())
    # one frame per agent step plus one per truncated episode; never one per agent or per stack slot
    assert replay.added == steps + truncated
    assert replay.frames.shape[1:] == (84, 84, 3)
    per_record = replay.nbytes / replay.capacity
    assert 84 * 84 * 3 <= per_record < 84 * 84 * 3 + 100


@pytest.mark.parametrize("setting, obs_type, screen_cells, frame", [
    (1, "pixels", True, (25, 25, 3)), (3, "pixels", True, (50, 50, 3)), (1, "pixels", False, (84, 84, 3)),
    (1, "grid", True, (25, 25, 4))])
def test_the_replay_stores_the_frames_the_rollouts_record(setting, obs_type, screen_cells, frame):
    """The run's replay frame (``replay_frame_shape``, what training builds its replay with) is the frame its
    rollouts record: a screen's cells where the networks read screens per cell, else a whole frame."""
    from formation.recipe.config import RunConfig
    from formation.recipe.team import reads_cells, replay_frame_shape

    run = RunConfig.from_dict({"game": {"setting": setting, "obs_type": obs_type, "frame_stack": 4},
                               "train": {"screen_cells": screen_cells, "obstacle_forecast": screen_cells}})
    assert replay_frame_shape(run) == frame
    rollout = GameRollout(run.game, 2, screen_cells=reads_cells(run))
    assert rollout.frame_shape == frame
    chunk = rollout.step(np.zeros((2, 2), np.int64))
    assert chunk.frames.shape[1:] == frame
    FrameReplay(10, replay_frame_shape(run), 2, 4).add(chunk)  # the replay takes them


def test_a_replay_of_cells_takes_11x_less_memory_on_setting_1_pixels():
    """Setting 1 from pixels (the networks read 25x25 cells): the replay's frames take 84*84/(25*25) = 11.3x
    fewer bytes than whole screens; setting 3's 50x50 cells 2.8x fewer."""
    from formation.recipe.config import RunConfig
    from formation.recipe.team import replay_frame_shape

    capacity = 1000
    ratios = {}
    for setting in (1, 3):
        run = RunConfig.from_dict({"game": {"setting": setting, "obs_type": "pixels", "frame_stack": 4}})
        cells = FrameReplay(capacity, replay_frame_shape(run), 2, 4)
        screens = FrameReplay(capacity, (84, 84, 3), 2, 4)  # what it stored before
        ratios[setting] = screens.frames.nbytes / cells.frames.nbytes
        assert cells.frames.nbytes == capacity * run.game.height * run.game.width * 3
    assert ratios[1] == 84 * 84 / (25 * 25) and ratios[1] > 11
    assert ratios[3] == 84 * 84 / (50 * 50) and ratios[3] > 2.8


def hand_chunk(rewards, terminated, truncated, stream=0, first_flags=None):
    n = len(rewards)
    first = np.zeros(n, bool) if first_flags is None else np.array(first_flags)
    return Chunk(streams=np.full(n, stream), frames=np.arange(n, dtype=np.uint8)[:, None, None, None] * np.ones(
        (1, 2, 2, 1), np.uint8), first=first, terminal=np.zeros(n, bool), actions=np.zeros((n, 2), np.int8),
        rewards=np.array(rewards, np.float32), terminated=np.array(terminated), truncated=np.array(truncated))


def test_n_step_returns_equal_a_hand_computation():
    replay = FrameReplay(100, (2, 2, 1), n_agents=2, frame_stack=1)
    r = [[1, 0], [2, -1], [4, 1], [8, -1], [16, 1]]
    # an episode of 5 steps that terminates on the last, then its terminal record
    replay.add(hand_chunk(r, [0, 0, 0, 0, 1], [0] * 5, first_flags=[1, 0, 0, 0, 0]))
    terminal = hand_chunk([[0, 0]], [0], [0])
    terminal.terminal[:] = True
    replay.add(terminal)
    g = 0.5
    returns, discounts, next_ids, ok = replay.n_step(np.arange(5), n=3, gamma=g)
    assert ok.all()
    np.testing.assert_allclose(returns[0], [1 + 2 * g + 4 * g * g, 0 - 1 * g + 1 * g * g])
    np.testing.assert_allclose(returns[2], [4 + 8 * g + 16 * g * g, 1 - g + g * g])
    np.testing.assert_allclose(returns[3], [8 + 16 * g, -1 + g])  # stops at the termination
    np.testing.assert_allclose(discounts[:2], [g ** 3] * 2)
    np.testing.assert_allclose(discounts[2:], [0, 0, 0])  # terminated inside the window: no bootstrap
    assert next_ids.tolist() == [3, 4, 5, 5, 5]
    # the terminal record is never a start
    assert not replay.n_step(np.array([5]), 3, g)[3][0]


def test_truncation_bootstraps_from_the_terminal_record():
    replay = FrameReplay(100, (2, 2, 1), n_agents=2, frame_stack=1)
    replay.add(hand_chunk([[1, 1], [1, 1]], [0, 0], [0, 1], first_flags=[1, 0]))
    terminal = hand_chunk([[0, 0]], [0], [0])
    terminal.terminal[:] = True
    replay.add(terminal)
    returns, discounts, next_ids, ok = replay.n_step(np.array([0]), n=5, gamma=0.9)
    assert ok[0] and next_ids[0] == 2
    np.testing.assert_allclose(returns[0], [1.9, 1.9])
    np.testing.assert_allclose(discounts[0], 0.81)


def test_unfinished_chains_are_not_sampled():
    replay = FrameReplay(100, (2, 2, 1), n_agents=2, frame_stack=1)
    replay.add(hand_chunk([[1, 1]] * 3, [0, 0, 0], [0, 0, 0], first_flags=[1, 0, 0]))
    _, _, _, ok = replay.n_step(np.arange(3), n=2, gamma=0.9)
    assert ok.tolist() == [True, False, False]  # records 1 and 2 still wait for successors


def test_prioritized_sampling_follows_priorities():
    tree = SumTree(5)
    tree.set(np.arange(5), np.array([0.0, 1.0, 0.0, 3.0, 0.0]))
    assert tree.total == 4.0
    draws = tree.find(np.random.default_rng(0).random(4000) * tree.total)
    assert set(draws.tolist()) == {1, 3}
    assert 0.7 < (draws == 3).mean() < 0.8


def test_a_stale_link_never_touches_the_record_that_reused_its_slot():
    replay = FrameReplay(4, (2, 2, 1), n_agents=2, frame_stack=1)
    replay.add(hand_chunk([[1, 1]], [0], [0], stream=7, first_flags=[1]))  # id 0, slot 0, stream 7
    # stream 8 fills the ring and wraps: id 4 reuses slot 0
    replay.add(hand_chunk([[1, 1]] * 4, [0] * 4, [0] * 4, stream=8, first_flags=[1, 0, 0, 0]))
    assert replay.ids[0] == 4 and replay.next[0] == -1
    replay.add(hand_chunk([[1, 1]], [0], [0], stream=8))  # id 5: links 4 -> 5 in slot 0
    assert replay.next[0] == 5
    # stream 7 goes on: its last record (id 0) is gone, and slot 0 must keep 4 -> 5
    replay.add(hand_chunk([[1, 1]], [0], [0], stream=7))
    assert replay.next[0] == 5


def test_a_terminated_step_needs_no_terminal_record():
    replay = FrameReplay(100, (2, 2, 1), n_agents=2, frame_stack=1)
    replay.add(hand_chunk([[1, 1], [2, 2]], [0, 1], [0, 0], first_flags=[1, 0]))  # no terminal record
    returns, discounts, _, ok = replay.n_step(np.arange(2), n=3, gamma=0.5)
    assert ok.tolist() == [True, True]
    np.testing.assert_allclose(returns, [[2, 2], [2, 2]])
    np.testing.assert_allclose(discounts, [0, 0])
    assert len(replay.sample(8, n_step=3, gamma=0.5)["ids"]) == 8


def test_labels_and_answers_come_back_with_their_own_steps():
    replay = FrameReplay(100, (2, 2, 1), n_agents=2, frame_stack=1)
    with_answers = hand_chunk([[0, 0]] * 6, [0] * 6, [0] * 6, first_flags=[1, 0, 0, 0, 0, 0])
    with_answers.labels = np.array([[k % 4, (k + 1) % 4] for k in range(6)], np.int8)
    with_answers.answers = np.array([[[-1] * 4, [(k + m) % 4 for m in range(4)]] for k in range(6)], np.int8)
    without = hand_chunk([[0, 0]] * 4, [0] * 3 + [1], [0] * 4, stream=1, first_flags=[1, 0, 0, 0])
    without.labels = np.full((4, 2), -1, np.int8)  # no answers
    chunk = concatenate([with_answers, without])
    assert chunk.answers.shape == (10, 2, 4) and (chunk.answers[6:] == -1).all()
    replay.add(chunk)
    batch = replay.sample(200, n_step=1, gamma=0.9)
    frame = batch["obs"][:, 0, 0, 0]  # hand_chunk's frames number the records of a chunk
    stream0 = batch["ids"] < 6
    k = frame[stream0].astype(np.int64)
    assert (batch["labels"][stream0] == np.stack([k % 4, (k + 1) % 4], 1)).all()
    assert (batch["answers"][stream0, 1] == (k[:, None] + np.arange(4)) % 4).all()
    assert (batch["answers"][stream0, 0] == -1).all()
    assert (batch["labels"][~stream0] == -1).all() and (batch["answers"][~stream0] == -1).all()
    assert stream0.any() and (~stream0).any()


def test_a_replay_shard_asks_ray_for_the_memory_it_takes_and_shards_spread_over_nodes():
    from formation.recipe.config import RunConfig
    from formation.recipe.team import replay_frame_shape
    from formation.rllib.algorithm import replay_shard

    run = RunConfig.load("configs/reward_only/setting3.yaml", {"resources.num_replay_shards": 4,
                                                                "resources.num_rollout_actors": 4})
    shard = replay_shard(run)
    capacity, frame_shape, agents, stack = shard["args"]
    assert (capacity, frame_shape, agents, stack) == (25_000, replay_frame_shape(run), 2, 4)
    # 25k records of a 50x50 board's cells, 3 colours: the frames alone are 187.5 MB
    assert 187_500_000 < shard["options"]["memory"] < 1.2 * 187_500_000
    assert shard["options"]["scheduling_strategy"] == "SPREAD"
