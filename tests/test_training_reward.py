"""Training rewards beside the game's (``train.reward_formation_kept``, ``train.team_reward``, ``train.shaping``):
the stored rewards change, the game's own reward (episode statistics, evaluation) does not."""

import numpy as np
import pytest

from formation.config import ConfigError, GameConfig
from formation.recipe.config import RunConfig
from formation.recipe.rollout import GameRollout
from formation.recipe.shaping import Potential


def play(rollout: GameRollout, steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list]:
    """Stored rewards of every step's records (not the truncation records), (steps, B, agents); whether each
    step ended its game (steps, B); and the episode statistics, for
    joint moves that take the team towards the destination together, or stay, and now and then a random move
    of the follower's own (so that some games reach, some collide and some break)."""
    rng = np.random.default_rng(seed)
    rewards, ended = [], []
    destination_column = rollout.config.destination[1]
    for _ in range(steps):
        towards = 1 + (rollout.game.positions[:, 0, 1] < destination_column)  # FL or FR
        towards[rollout.game.positions[:, 0, 1] == destination_column] = 0  # F
        move = np.where(rng.random(rollout.batch_size) < 0.3, 3, towards)
        moves = np.repeat(move[:, None], rollout.n_agents, axis=1)
        strays = rng.random(rollout.batch_size) < 0.2  # the follower's own random move: it may break the formation
        moves[strays, 1] = rng.integers(0, 4, strays.sum())
        chunk = rollout.step(moves)
        rewards.append(chunk.rewards[: rollout.batch_size])
        ended.append(chunk.terminated[: rollout.batch_size] | chunk.truncated[: rollout.batch_size])
    return np.stack(rewards), np.stack(ended), rollout.pop_episodes()


def test_the_kept_reward_and_the_team_reward_change_the_stored_rewards_and_not_the_games():
    config = GameConfig(setting=None, height=9, width=9, n_obstacles=1, obs_type="grid", frame_stack=2)
    paper, _, paper_episodes = play(GameRollout(config, 32, seed=3), 120)
    trained, _, episodes = play(GameRollout(config, 32, seed=3, reward_formation_kept=-0.5, team_reward=True), 120)
    paper, trained = paper.reshape(-1, paper.shape[-1]), trained.reshape(-1, trained.shape[-1])
    # the game's reward (GAME.md): the follower's is >= 0 where the formation held, the leader's 50 more on reach
    kept, reached = paper[:, 1] >= 0, paper[:, 0] >= 40
    assert reached.sum() > 10 and kept.sum() > 100 and (~kept).sum() > 10
    # the leader: the kept step's +1 became -0.5; the follower also gets the leader's reach reward
    assert np.allclose(trained[:, 0] - paper[:, 0], -1.5 * kept)
    assert np.allclose(trained[:, 1] - paper[:, 1], -1.5 * kept + 50.0 * reached)
    # the episode statistics keep the game's own reward
    assert [e["returns"] for e in episodes] == [e["returns"] for e in paper_episodes]


def test_the_shaping_telescopes_to_a_reach_and_charges_the_distance_left_at_a_collision_or_break():
    """Over an episode the leader's discounted shaping sums to gamma^T Phi(s_T) - Phi(s_0): the start's 8 steps
    to go (9x9 board) where it reaches, less where a collision or break ends it, as Phi(s_T) is kept there and
    nothing bootstraps after it (docs/RECIPE.md, "Distance shaping")."""
    config = GameConfig(setting=None, height=9, width=9, n_obstacles=1, obs_type="grid", frame_stack=2)
    gamma, games, start = 0.97, 32, config.height - 1  # the leader starts on the bottom row, 8 steps to go
    paper, ended, _ = play(GameRollout(config, games, seed=3), 150)
    shaped, _, _ = play(GameRollout(config, games, seed=3, potential=Potential(config), shaping=1.0,
                                    gamma=gamma), 150)
    assert np.allclose(shaped[..., 1], paper[..., 1])  # followers' potential is 0
    sums = {"reached": [], "other": []}
    for g in range(games):
        total, t = 0.0, 0
        for step in range(len(paper)):
            total += gamma ** t * (shaped[step, g, 0] - paper[step, g, 0])
            t += 1
            if ended[step, g]:
                sums["reached" if paper[step, g, 0] >= 40 else "other"].append((total, gamma ** t))
                total, t = 0.0, 0
    assert len(sums["reached"]) > 10 and len(sums["other"]) > 10
    assert np.allclose([total for total, _ in sums["reached"]], start, atol=1e-4)
    # a collision or break at a cell d >= 1 steps from the destination: start - gamma^T d
    assert all(total <= start - discount + 1e-4 for total, discount in sums["other"])


@pytest.mark.parametrize("key, value, allowed", [("reward_formation_kept", "x", "null or a number"),
                                                 ("team_reward", 1, "true, false")])
def test_a_bad_training_reward_is_refused_in_one_line(key, value, allowed):
    with pytest.raises(ConfigError, match=rf"^train\.{key}: .* is not allowed; allowed: {allowed}"):
        RunConfig.from_dict({"train": {key: value}})


@pytest.mark.parametrize("key, value", [("reward_formation_kept", 0.0), ("team_reward", True)])
def test_rllibs_stock_dqn_refuses_a_training_reward_it_would_not_apply(key, value):
    stock = {"path": "stock", "shaping": 0, "prioritized": False, "follower_answers_leader": False,
             "reward_formation_kept": None, "team_reward": False}
    RunConfig.from_dict({"train": stock})
    with pytest.raises(ConfigError, match=rf"^train\.path: stock .*{key}: "):
        RunConfig.from_dict({"train": {**stock, key: value}})
