"""RLlib as its users expect it: the algorithm's config is the one source of truth, options the formation path does not
honour are refused in one line, callbacks fire (or are refused), results carry RLlib's standard keys, and every
module's forward passes return env actions."""

import math

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from formation.config import ConfigError  # noqa: E402
from formation.recipe.config import RunConfig  # noqa: E402

SMOKE = "configs/smoke.yaml"


def smoke_config(**overrides):
    from formation.rllib.algorithm import build_algorithm_config

    return build_algorithm_config(RunConfig.load(SMOKE, overrides))


# --------------------------------------------------------------------------- one source of truth
def test_the_config_built_from_a_run_is_that_run():
    run = RunConfig.load(SMOKE)
    config = smoke_config()
    assert config.run == run
    t, res = run.train, run.resources
    assert (config.lr, config.gamma, config.n_step, config.train_batch_size) == (t.lr, t.gamma, t.n_step, t.batch_size)
    assert config.target_network_update_freq == t.target_update_every
    assert config.num_steps_sampled_before_learning_starts == t.learning_starts
    assert config.epsilon == [(0, t.epsilon_start), (t.epsilon_env_steps, t.epsilon_end)]
    assert (config.num_env_runners, config.num_envs_per_env_runner) == (res.num_rollout_actors, res.games_per_actor)
    assert config.merge_env_runner_states is False  # no per-iteration barrier on the rollout actors' states


def test_rllib_setters_set_the_run_config_that_rollout_actors_and_the_learner_read():
    from formation.recipe.collect import epsilon_at
    from formation.rllib.rollout_actor import RolloutActor

    config = (smoke_config()
              .training(n_step=7, gamma=0.5, lr=0.123, train_batch_size=16, target_network_update_freq=9,
                        grad_clip=3.0, num_steps_sampled_before_learning_starts=11, epsilon=[(0, 0.5), (100, 0.01)])
              .env_runners(num_env_runners=1, num_envs_per_env_runner=4)
              .debugging(seed=5))
    t = config.run.train
    assert (t.n_step, t.gamma, t.lr, t.batch_size, t.target_update_every, t.grad_clip, t.learning_starts, t.seed) == \
        (7, 0.5, 0.123, 16, 9, 3.0, 11, 5)
    assert (t.epsilon_start, t.epsilon_end, t.epsilon_env_steps) == (0.5, 0.01, 100)
    assert (config.run.resources.num_rollout_actors, config.run.resources.games_per_actor) == (1, 4)
    assert config.formation_run == config.run.to_dict()  # what train.py and the card save
    assert config.copy(copy_frozen=True).run == config.run
    # a rollout actor shapes with this gamma, explores on this schedule and plays this many games
    actor = RolloutActor(config=config)
    assert actor.run == config.run
    assert actor.rollout.gamma == 0.5 and actor.rollout.batch_size == 4
    assert epsilon_at(50, actor.run.train) == pytest.approx(0.255)
    # the learner pulls batches of this size, n-step and gamma (the RLlib fields themselves)
    assert (config.train_batch_size, config.n_step, config.gamma) == (16, 7, 0.5)
    # train_batch_size_per_learner is RLlib's: train.batch_size is the total over the learners
    assert config.training(train_batch_size_per_learner=24).run.train.batch_size == 24
    values = config.formation_run
    values["resources"].update(num_replay_shards=2, num_rollout_actors=2)
    config.formation_run = values
    config.learners(num_learners=2).training(train_batch_size_per_learner=24)
    assert (config.run.resources.num_learners, config.run.train.batch_size) == (2, 48)
    assert config.train_batch_size_per_learner == 24


@pytest.mark.parametrize("kwargs, key", [({"gamma": 5}, "train.gamma"), ({"lr": -1.0}, "train.lr"),
                                         ({"n_step": 0}, "train.n_step"),
                                         ({"epsilon": [(0, 1.0), (5, 0.5), (10, 0.0)]}, "epsilon")])
def test_invalid_values_are_the_run_configs_one_line_error(kwargs, key):
    config = smoke_config()
    with pytest.raises(ConfigError, match=key) as err:
        config.training(**kwargs)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("method, kwargs", [
    ("training", {"double_q": False}), ("training", {"dueling": False}), ("training", {"tau": 0.5}),
    ("training", {"num_atoms": 51}), ("training", {"noisy": True}), ("training", {"td_error_loss_fn": "mse"}),
    ("training", {"training_intensity": 4.0}), ("training", {"replay_buffer_config": {"capacity": 10}}),
    ("env_runners", {"rollout_fragment_length": 50}), ("evaluation", {"evaluation_interval": 1}),
    ("learners", {"num_cpus_per_learner": 2}), ("environment", {"env": "CartPole-v1"}),
    ("framework", {"torch_compile_learner": True}),
    ("training", {"optimizer": {"type": "sgd"}}), ("env_runners", {"env_to_module_connector": lambda env: []}),
    ("env_runners", {"module_to_env_connector": lambda env: []}), ("training", {"learner_connector": lambda s: []})])
def test_options_the_formation_path_does_not_honour_are_refused_in_one_line(method, kwargs):
    config = smoke_config()
    (key,) = kwargs
    with pytest.raises(ConfigError, match=key) as err:
        getattr(config, method)(**kwargs)
    assert "\n" not in str(err.value) and "docs/CONFIG.md" in str(err.value)
    # the values the path does honour stay accepted
    config.training(double_q=True, dueling=True, tau=1.0)


def test_tunes_round_trip_through_a_dict_keeps_the_run():
    from formation.rllib.algorithm import FormationDQN, FormationDQNConfig

    config = smoke_config().training(lr=3e-4, n_step=2)
    copy = FormationDQNConfig().update_from_dict(config.to_dict())
    assert copy.run == config.run
    bundles = FormationDQN.default_resource_request(config.to_dict()).bundles
    assert sum(b.get("CPU", 0) for b in bundles) == pytest.approx(1 + 2 * 0.5 + 1)  # main, 2 actors, learner


def test_the_stock_path_keeps_rllibs_dqn_and_the_same_source_of_truth():
    stock = {"train.path": "stock", "train.shaping": 0, "train.reward_formation_kept": None, "train.team_reward": False,
             "train.prioritized": False, "train.follower_answers_leader": False}
    config = smoke_config(**stock)
    assert config.run == RunConfig.load(SMOKE, stock)
    config.training(lr=0.01, double_q=False)  # RLlib's own DQN honours both
    assert config.run.train.lr == 0.01
    # its target_network_update_freq counts env steps: not the run config's (learner updates)
    assert config.target_network_update_freq != config.run.train.target_update_every


# --------------------------------------------------------------------------- callbacks
def test_callbacks_on_env_runner_hooks_are_refused_in_one_line():
    from ray.rllib.callbacks.callbacks import RLlibCallback

    class Episodes(RLlibCallback):
        def on_episode_end(self, **kwargs):
            pass

    class Results(RLlibCallback):
        def on_train_result(self, **kwargs):
            pass

    config = smoke_config()
    with pytest.raises(ConfigError, match="Episodes.on_episode_end") as err:
        config.callbacks(Episodes)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="on_sample_end"):
        config.callbacks(on_sample_end=lambda **kwargs: None)
    config.callbacks(Results)  # algorithm-level hooks fire
    assert config.callbacks_class is Results


class Recorder:
    """Algorithm-level callbacks, recorded in the algorithm (callbacks run in its process)."""

    @staticmethod
    def make():
        from ray.rllib.callbacks.callbacks import RLlibCallback

        class Recording(RLlibCallback):
            def on_algorithm_init(self, *, algorithm, **kwargs):
                algorithm.fired = ["on_algorithm_init"]

            def on_train_result(self, *, algorithm, result, **kwargs):
                algorithm.fired.append("on_train_result")
                result["seen_by_callback"] = True

            def on_evaluate_start(self, *, algorithm, **kwargs):
                algorithm.fired.append("on_evaluate_start")

            def on_evaluate_end(self, *, algorithm, evaluation_metrics, **kwargs):
                algorithm.fired.append("on_evaluate_end")
                algorithm.evaluation_metrics = evaluation_metrics

        return Recording


def test_algorithm_callbacks_fire_and_results_carry_rllibs_standard_keys(cluster):
    config = smoke_config(**{"resources.num_rollout_actors": 1, "resources.cpus_per_rollout_actor": 1.0,
                             "train.learning_starts": 64, "eval.every_env_steps": 64, "eval.episodes": 10,
                             "eval.gif_episodes": 0})
    algo = config.callbacks(Recorder.make()).build_algo()
    try:
        assert algo.fired == ["on_algorithm_init"]
        first = algo.train()
        # greedy results under "evaluation" from the first iteration, NaN before the first evaluation
        for key in ("success", "leader_collision", "follower_collision", "formation_broken", "timeout"):
            assert key in first["evaluation"]
        assert "episode_return_mean" in first["evaluation"]["env_runners"]
        for key in ("episode_return_mean", "episode_len_mean", "num_episodes", "num_env_steps_sampled",
                    "num_env_steps_sampled_lifetime", "num_episodes_lifetime"):
            assert key in first["env_runners"], key
        assert first["seen_by_callback"] and algo.fired.count("on_train_result") == 1
        result = first
        while not algo.last_eval or algo.counters["episodes"] == 0:
            result = algo.train()
        # RLlib 2.60's windowed means cover one iteration's episodes (NaN in an iteration that ends none), so check
        # the means on an iteration that ended some
        for _ in range(50):
            result = algo.train()
            if result["env_runners"]["num_episodes"] > 0:
                break
        assert {"on_evaluate_start", "on_evaluate_end"} <= set(algo.fired)
        assert algo.evaluation_metrics["success"] == algo.last_eval["success"]
        assert result["evaluation"]["success"] == algo.last_eval["success"]
        returns = algo.last_eval["return_mean"]
        assert result["evaluation"]["env_runners"]["episode_return_mean"] == pytest.approx(sum(returns.values()))
        runners = result["env_runners"]
        assert runners["num_env_steps_sampled_lifetime"] == algo.counters["env_steps"]
        assert runners["num_episodes_lifetime"] == algo.counters["episodes"]
        assert math.isfinite(runners["episode_return_mean"]) and runners["episode_len_mean"] >= 1
        assert set(runners["agent_episode_returns_mean"]) == {"leader", "follower"}
        # every rollout actor's epsilon clock is the run's env steps (RLlib syncs it after each iteration)
        clocks = algo.env_runner_group.foreach_env_runner(lambda w: w.num_env_steps_sampled_lifetime,
                                                          local_env_runner=False)
        assert all(c >= algo.counters["env_steps"] - 64 * 2 for c in clocks), (clocks, algo.counters)
    finally:
        algo.stop()


# --------------------------------------------------------------------------- modules act in env actions
def test_every_modules_forward_passes_return_env_actions():
    import torch
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec

    from formation.rllib.algorithm import module_specs

    run = RunConfig.load(SMOKE)
    assert run.train.follower_answers_leader
    modules = MultiRLModuleSpec(rl_module_specs=module_specs(run, inference_only=True)).build()
    obs_space = modules["leader"].observation_space
    obs = torch.from_numpy(np.stack([obs_space.sample() for _ in range(64)]))
    for m in ("leader", "follower"):
        module = modules[m]
        assert module.action_space.n == 4
        q = module.q_network(obs)
        assert q.shape[-1] == (16 if m == "follower" else 4)
        with torch.no_grad():
            greedy = module.forward_inference({Columns.OBS: obs})[Columns.ACTIONS]
            exploring = module.forward_exploration({Columns.OBS: obs}, t=0)[Columns.ACTIONS]
        assert greedy.min() >= 0 and greedy.max() <= 3 and exploring.min() >= 0 and exploring.max() <= 3
        # the follower's: the own move of its best (leader's move, own move) pair
        assert torch.equal(greedy, q.argmax(-1) % 4)


# --------------------------------------------------------------------------- the replay keeps the cells
def test_a_rollout_actor_acts_on_whole_screens_and_pushes_only_their_cells(rollout_actor, monkeypatch):
    """Where the networks read screens per cell, a rollout actor's records (its pushes to the replay) hold the
    cells of the screens its renderer drew, in the replay's frame shape, while its modules act on whole
    screens (their observation space). No Ray cluster: the replay handle is a stand-in."""
    from types import SimpleNamespace

    import torch

    from formation.recipe.qnet import ScreenCells
    from formation.recipe.team import replay_frame_shape

    actor = rollout_actor({"game.obs_type": "pixels", "train.steps_per_sample": 3})
    run, rollout = actor.run, actor.rollout
    board = (run.game.height, run.game.width)
    assert replay_frame_shape(run) == rollout.frame_shape == (*board, 3)
    pushed, shown, acted_on = [], [], []
    actor.set_replay(SimpleNamespace(add=SimpleNamespace(remote=pushed.append)))
    step, act = rollout.step, actor.collector.actions

    def watched_step(*args, **kwargs):
        shown.append(rollout.observer.renderer.screens.copy())  # the screens of the state the step leaves
        return step(*args, **kwargs)

    def watched_actions(networks, env_steps):
        acted_on.append(rollout.observations.shape)
        return act(networks, env_steps)

    monkeypatch.setattr(rollout, "step", watched_step)
    monkeypatch.setattr(actor.collector, "actions", watched_actions)
    actor.sample()
    screen = actor.module["leader"].observation_space.shape
    assert screen == (84, 84, 3 * run.game.frame_stack) and acted_on == [(len(shown[0]), *screen)] * 3
    chunk, = pushed
    assert chunk.frames.shape[1:] == (*board, 3)
    reader = ScreenCells((84, 84, 3), board)
    # each step's first records, one per game, are the frames shown before it (terminal records follow them)
    starts = np.flatnonzero(~chunk.terminal)
    games = rollout.batch_size
    assert len(starts) == 3 * games
    for i, screens in enumerate(shown):
        np.testing.assert_array_equal(chunk.frames[starts[i * games:(i + 1) * games]],
                                      reader(torch.from_numpy(screens)).numpy())


# --------------------------------------------------------------------------- RLlib's own restore
def test_rllibs_from_checkpoint_restores_a_run_that_evaluates_as_the_run_did(cluster, smoke_run):
    """``FormationDQN.from_checkpoint`` (RLlib's ``Algorithm.from_checkpoint``) of a run folder's checkpoint: the
    run's config, counters and weights, so its greedy evaluation is the one the run wrote (the same scenarios);
    ``resources`` replaces the saved run's, and a run the Ray at hand cannot hold is refused in one line."""
    import dataclasses
    import json

    from formation.rllib.algorithm import FormationDQN

    checkpoint = str(smoke_run / "checkpoint")
    with pytest.raises(ConfigError, match=r"^resources\.num_gpus_per_learner: 1 GPU asked, the Ray cluster has 0"):
        FormationDQN.from_checkpoint(checkpoint, resources={"num_gpus_per_learner": 1})
    with pytest.raises(ConfigError, match=r"^resources\.num_rollout_actors: -1 is not allowed"):
        FormationDQN.from_checkpoint(checkpoint, resources={"num_rollout_actors": -1})
    result = json.loads((smoke_run / "result.json").read_text())
    algo = FormationDQN.from_checkpoint(checkpoint, resources={"num_rollout_actors": 1})
    try:
        saved = RunConfig.load_saved(smoke_run / "config.yaml")
        assert algo.run == dataclasses.replace(saved, resources=dataclasses.replace(saved.resources,
                                                                                    num_rollout_actors=1))
        assert algo.env_runner_group.num_remote_env_runners() == 1
        assert algo.counters["env_steps"] == result["env_steps"]
        assert algo.evaluate_greedy()["success"] == result["greedy"]["success"]
    finally:
        algo.stop()


def test_a_rollout_actor_waits_for_a_replay_shard_that_falls_behind(cluster, rollout_actor):
    """Bounded in-flight pushes: at most ``ADDS_IN_FLIGHT`` unacknowledged, then the actor waits for the oldest
    (counted as its ``push_wait`` stage) rather than piling records up in the object store."""
    import time

    from formation.rllib.rollout_actor import ADDS_IN_FLIGHT

    @ray.remote(num_cpus=0)
    class SlowReplay:
        def add(self, chunk) -> int:
            time.sleep(0.5)
            return len(chunk)

    actor = rollout_actor({"train.steps_per_sample": 1})
    actor.set_replay(SlowReplay.remote())
    results = [actor.sample() for _ in range(ADDS_IN_FLIGHT)]
    assert all("push_wait" not in r["seconds"] for r in results) and len(actor._adds) == ADDS_IN_FLIGHT
    oldest = actor._adds[0]
    result = actor.sample()
    assert "push_wait" in result["seconds"] and len(actor._adds) == ADDS_IN_FLIGHT
    ready, _ = ray.wait([oldest], timeout=0)
    assert ready == [oldest]  # it returned only once the replay had taken its oldest push
