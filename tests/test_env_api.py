"""The PettingZoo and RLlib views: the libraries' own checks, and agreement with the batched core."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, seed_test, state_test

import formation.env as fenv
import formation.env.pettingzoo as pettingzoo_card
from formation.config import GameConfig
from formation.game import BatchedGame, GridRenderer, Observer, ScreenRenderer

# PettingZoo recommends names like "player_0"; the rules fix "leader" and "follower".
NAMING = "ignore:We recommend agents to be named"


# --------------------------------------------------------------------------- PettingZoo's own tests
ENV_ARGS = [dict(setting=1), dict(setting=2), dict(setting=3), dict(setting=4),
            dict(setting=1, n_followers=2), dict(setting=4, n_followers=2),
            dict(setting=1, n_followers=3), dict(setting=2, n_followers=3),
            dict(setting=3, n_followers=4), dict(setting=4, n_followers=4),
            dict(setting=2, obs_type="grid", frame_stack=2)]


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("args", ENV_ARGS, ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_parallel_api_test(args):
    parallel_api_test(fenv.parallel_env(**args), num_cycles=60)


def test_parallel_api_test_through_truncation():
    # No obstacles and a limit of 2 steps: many of its episodes end by truncation.
    env = fenv.parallel_env(1, max_steps=2, n_obstacles=0)
    parallel_api_test(env, num_cycles=20)


@pytest.mark.parametrize("args", ENV_ARGS, ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_parallel_seed_test(args):
    parallel_seed_test(lambda: fenv.parallel_env(**args), num_cycles=60)


@pytest.mark.filterwarnings(NAMING)
@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("args", [dict(setting=1), dict(setting=4), dict(setting=2, n_followers=2),
                                  dict(setting=1, n_followers=4)],
                         ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_aec_api_test(args):
    api_test(fenv.env(**args), num_cycles=40)


@pytest.mark.parametrize("args", [dict(setting=1), dict(setting=2, n_followers=2)],
                         ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_aec_seed_test(args):
    seed_test(lambda: fenv.env(**args), num_cycles=40)


# --------------------------------------------------------------------------- state() and state_space
STATE_ARGS = [dict(setting=1), dict(setting=4, n_followers=2), dict(setting=3, n_followers=3),
              dict(setting=2, obs_type="grid", frame_stack=2),
              dict(setting=1, max_steps=2, n_obstacles=0)]


@pytest.mark.filterwarnings(NAMING)
@pytest.mark.filterwarnings("error")  # PettingZoo's state checks warn (all zeros, bad shapes): fail on them
@pytest.mark.parametrize("args", STATE_ARGS, ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_state_test(args):
    state_test(fenv.env(**args), fenv.parallel_env(**args), num_cycles=40)


def test_state_space_is_one_frame_of_the_observation():
    pixels = fenv.parallel_env(1)
    assert pixels.state_space == gymnasium.spaces.Box(0, 255, (84, 84, 3), np.uint8)
    grid = fenv.parallel_env(3, obs_type="grid")
    assert grid.state_space == gymnasium.spaces.Box(0, 1, (50, 50, 4), np.uint8)
    aec = fenv.env(3, obs_type="grid")  # PettingZoo's conversion carries it
    assert aec.state_space == grid.state_space


def _spec_screen(scenario: dict, H: int, W: int) -> np.ndarray:
    """The screen drawn straight from its formula (docs/GAME.md, 'Screen (observation)'), not by the renderer."""
    screen = np.zeros((84, 84, 3), np.uint8)

    def paint(r, c, colour):
        screen[(168 * r + H) // (2 * H):(168 * (r + 1) + H) // (2 * H),
               (168 * c + W) // (2 * W):(168 * (c + 1) + W) // (2 * W)] = colour

    paint(0, W // 2, (255, 255, 255))
    for r, c, _v in scenario["obstacles"]:
        paint(r, c, (255, 0, 0))
    for r, c in scenario.get("followers", [scenario.get("follower")]):
        paint(r, c, (0, 255, 0))
    paint(*scenario["leader"], (0, 0, 255))
    return screen


@pytest.mark.parametrize("args", [dict(setting=1), dict(setting=3, n_followers=2)],
                         ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_state_is_the_present_screen(args):
    env = fenv.parallel_env(render_mode="rgb_array", **args)
    config = env.config
    obs, _ = env.reset(seed=5)
    rng = np.random.default_rng(0)
    steps = 0
    while env.agents and steps < 30:
        state = env.state()
        assert state.dtype == np.uint8 and env.state_space.contains(state)
        np.testing.assert_array_equal(state, _spec_screen(env.scenario(), config.height, config.width))
        np.testing.assert_array_equal(state, env.render())
        np.testing.assert_array_equal(state, obs["leader"][..., -3:])  # the newest frame of the stack
        # Drawn by a fresh renderer from the scenario alone: the state holds nothing else.
        game = BatchedGame(config, 1)
        game.load([env.scenario()])
        np.testing.assert_array_equal(state, ScreenRenderer(game).render()[0])
        obs, *_ = env.step({a: 3 if steps % 2 else int(rng.integers(0, 4)) for a in env.agents})
        assert not np.array_equal(env.state(), state)  # obstacles always move
        steps += 1
    assert steps >= 2


def test_state_is_the_present_grid():
    env = fenv.parallel_env(2, obs_type="grid", frame_stack=2)
    config = env.config
    obs, _ = env.reset(seed=1)
    for _ in range(5):
        state = env.state()
        assert state.shape == (25, 25, 4) and env.state_space.contains(state)
        np.testing.assert_array_equal(state, obs["follower"][..., -4:])
        scenario = env.scenario()
        planes = np.zeros((25, 25, 4), np.uint8)
        planes[0, 12, 0] = 1
        for r, c, _v in scenario["obstacles"]:
            planes[r, c, 1] = 1
        planes[(*scenario["follower"], 2)] = 1
        planes[(*scenario["leader"], 3)] = 1
        np.testing.assert_array_equal(state, planes)
        game = BatchedGame(config, 1)
        game.load([scenario])
        np.testing.assert_array_equal(state, GridRenderer(game).render()[0])
        obs, *_ = env.step({a: 3 for a in env.agents})
        assert not np.array_equal(env.state(), state)
        if not env.agents:
            break


def test_state_is_a_copy_and_survives_the_episode_end():
    env = fenv.parallel_env(1)
    env.reset(options={"scenario": {"leader": [1, 12], "follower": [1, 10], "obstacles": []}})
    state = env.state()
    state[:] = 0
    assert env.state().any()
    env.step({"leader": 0, "follower": 0})  # the leader reaches the destination
    assert not env.agents
    final = env.state()
    leader_px = final[(168 * 0 + 25) // 50, (168 * 12 + 25) // 50]
    assert leader_px.tolist() == [0, 0, 255]  # the leader is drawn on the destination


def test_state_through_the_aec_env():
    aec = fenv.env(1)
    aec.reset(seed=2)
    par = fenv.parallel_env(1)
    par.reset(seed=2)
    np.testing.assert_array_equal(aec.state(), par.state())
    aec.step(1)
    np.testing.assert_array_equal(aec.state(), par.state())  # nothing moves until every agent acted
    aec.step(2)
    par.step({"leader": 1, "follower": 2})
    np.testing.assert_array_equal(aec.state(), par.state())
    assert aec.state_space.contains(aec.state())


def test_seeded_states_repeat():
    def run():
        env = fenv.parallel_env(3, obs_type="grid", frame_stack=1)
        env.reset(seed=9)
        states = [env.state()]
        for _ in range(6):
            env.step({a: 3 for a in env.agents})
            states.append(env.state())
            if not env.agents:
                break
        return np.stack(states)

    np.testing.assert_array_equal(run(), run())


def test_versioned_name_and_card():
    env = fenv.parallel_env(1)
    name = env.metadata["name"]
    assert name == "formation_v2"
    assert env.metadata["render_modes"] == ["rgb_array"]
    doc = pettingzoo_card.__doc__
    assert f"``{name}``" in doc and "v2:" in doc and "v1:" in doc and "state shape" in doc and "parallel API" in doc
    assert fenv.env(1).metadata["name"] == name


def test_aec_env_plays_a_scenario():
    env = fenv.env(1)
    env.reset(options={"scenario": {"leader": [1, 12], "follower": [1, 10], "obstacles": []}})
    assert env.agent_selection == "leader"
    env.step(0)
    env.step(0)
    _, reward, terminated, truncated, info = env.last()
    assert terminated and not truncated
    assert env.rewards == {"leader": 51.0, "follower": 1.0}
    assert env.infos["leader"]["success"]


def test_reset_ignores_unknown_option_keys():
    env = fenv.parallel_env(1)
    a, _ = env.reset(seed=3, options={"other": 1})
    b, _ = env.reset(seed=3)
    np.testing.assert_array_equal(a["leader"], b["leader"])


def test_step_needs_every_live_agent():
    env = fenv.parallel_env(1)
    env.reset(seed=0)
    with pytest.raises(ValueError):
        env.step({"leader": 0})
    with pytest.raises(ValueError):
        env.step({"leader": 0, "follower": 4})


# --------------------------------------------------------------------------- batched core == single envs
@pytest.mark.parametrize("args", [dict(setting=1), dict(setting=4), dict(setting=2, n_followers=2),
                                  dict(setting=3, obs_type="grid", frame_stack=2)],
                         ids=lambda a: "-".join(f"{k}={v}" for k, v in a.items()))
def test_batched_core_agrees_with_single_envs(args):
    B = 8
    config = GameConfig.from_setting(**args)
    source = BatchedGame(config, B, seed=10)  # where the scenarios come from
    source.reset()
    game = BatchedGame(config, B)
    game.load([source.scenario(i) for i in range(B)])
    observer = Observer(game)
    batch_obs = observer.observe(reset=np.ones(B, bool))
    envs = [fenv.parallel_env(**args) for _ in range(B)]
    agents = envs[0].possible_agents
    single_obs = [e.reset(options={"scenario": source.scenario(i).to_dict()})[0] for i, e in enumerate(envs)]
    for i in range(B):
        for a in agents:
            np.testing.assert_array_equal(single_obs[i][a], batch_obs[i])
    rng = np.random.default_rng(0)
    episodes = 0
    for _ in range(80):
        actions = rng.integers(0, 4, size=(B, len(agents)))
        # Same moves for every agent half of the time, so that some episodes last.
        same = rng.random(B) < 0.5
        actions[same] = actions[same, :1]
        game.step(actions)
        results = [e.step(dict(zip(agents, actions[i].tolist()))) for i, e in enumerate(envs)]
        for i, (_obs, rew, term, trunc, info) in enumerate(results):
            assert [info[a]["position"] for a in agents] == game.positions[i].tolist()
            assert [rew[a] for a in agents] == game.rewards[i].tolist()
            assert [info[a]["collided"] for a in agents] == game.collided[i].tolist()
            assert all(term[a] == bool(game.terminated[i]) for a in agents)
            assert all(trunc[a] == bool(game.truncated[i]) for a in agents)
            assert info["leader"]["formation_kept"] == bool(game.formation_kept[i])
            assert info["leader"]["reached"] == bool(game.reached[i])
            assert info["leader"]["success"] == bool(game.success[i])
            assert envs[i].scenario() == game.scenario(i).to_dict()
        done = game.done.copy()
        if done.any():
            episodes += int(done.sum())
            source.reset(mask=done)
            game.load([source.scenario(i) for i in np.flatnonzero(done)], mask=done)
        batch_obs = observer.observe(reset=done)
        for i, (obs, *_rest) in enumerate(results):
            if done[i]:
                obs, _ = envs[i].reset(options={"scenario": source.scenario(i).to_dict()})
            for a in agents:
                np.testing.assert_array_equal(obs[a], batch_obs[i])
    assert episodes >= B  # episode boundaries were crossed


# --------------------------------------------------------------------------- RLlib
@pytest.fixture(scope="module")
def rllib_env():
    pytest.importorskip("ray.rllib")
    from formation.rllib.env import FormationMultiAgentEnv, register

    register()
    return FormationMultiAgentEnv


@pytest.mark.parametrize("env_config", [{"setting": 1}, {"setting": 2, "n_followers": 2},
                                        {"setting": 1, "max_steps": 1},  # every first step ends
                                        {"setting": 3, "obs_type": "grid"}])
def test_rllib_env_checker(rllib_env, env_config):
    from ray.rllib.utils.pre_checks.env import check_multiagent_environments

    for _ in range(3):  # the checker samples random actions: some first steps end the episode
        env = rllib_env(env_config)
        check_multiagent_environments(env)


def test_rllib_env_reports_all_done(rllib_env):
    env = rllib_env({"setting": 1})
    obs, infos = env.reset(options={"scenario": {"leader": [1, 12], "follower": [1, 10], "obstacles": []}})
    assert set(obs) == set(env.possible_agents) == {"leader", "follower"}
    obs, rew, term, trunc, infos = env.step({"leader": 0, "follower": 0})
    assert term == {"leader": True, "follower": True, "__all__": True}
    assert trunc == {"leader": False, "follower": False, "__all__": False}
    assert rew == {"leader": 51.0, "follower": 1.0}
    assert env.get_observation_space("leader").contains(obs["leader"])
    obs, _ = env.reset(seed=1)
    assert set(obs) == set(env.agents) == {"leader", "follower"}


def test_rllib_multi_agent_env_runner(rllib_env):
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

    config = (
        PPOConfig()
        .environment("formation", env_config={"setting": 1, "max_steps": 6})
        .multi_agent(policies={"leader", "follower"}, policy_mapping_fn=lambda aid, *a, **k: aid)
        .env_runners(num_env_runners=0, num_envs_per_env_runner=2)
    )
    runner = MultiAgentEnvRunner(config=config)
    try:
        # The default RLModule takes float inputs; the env's screens are uint8, so the runner
        # samples random actions: this checks the env inside RLlib's loop, not a model.
        episodes = runner.sample(num_timesteps=30, random_actions=True)
        assert sum(e.env_steps() for e in episodes) >= 30
        for episode in episodes:
            assert set(episode.agent_ids) == {"leader", "follower"}
            assert 1 <= episode.env_steps() <= 6
            rewards = episode.get_rewards()
            assert set(rewards) == {"leader", "follower"}
            for r in rewards.values():
                assert set(np.unique(r).tolist()) <= {-2.0, -1.0, 0.0, 1.0, 50.0, 51.0}
        assert any(e.is_done for e in episodes)
    finally:
        runner.stop()
