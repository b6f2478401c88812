"""Ray Tune over the algorithm: a grid over ``lr`` on the smoke config, each trial trained with its own learning
rate, and the greedy success read from Tune's results.

The grid has one value, not the config's own (smoke: 1e-3), so that the learner's lr tells the grid's from the
config's: a trial costs a Tune actor, a rollout actor, the replay and the learner, about a minute of a loaded
2-core machine (two trials were the slowest test of the suite)."""

import pytest

ray = pytest.importorskip("ray")
tune = pytest.importorskip("ray.tune")

from formation.recipe.config import RunConfig  # noqa: E402

LRS = [3e-4]


def test_a_grid_over_lr_runs_each_trial_with_its_own_lr_and_reports_greedy_success(cluster, tmp_path):
    from formation.rllib.algorithm import FormationDQN, build_algorithm_config

    assert RunConfig.load("configs/smoke.yaml").train.lr not in LRS  # else the trial's lr would prove nothing

    # sized for 2 CPUs: the trial's process, one rollout actor and the learner; an evaluation at every sample
    run = RunConfig.load("configs/smoke.yaml", {
        "resources.num_rollout_actors": 1, "resources.cpus_per_rollout_actor": 0.5, "train.learning_starts": 64,
        "eval.every_env_steps": 64, "eval.episodes": 10, "eval.gif_episodes": 0})
    config = build_algorithm_config(run).resources(num_cpus_for_main_process=0.5)
    config.training(lr=tune.grid_search(LRS))
    tuner = tune.Tuner(
        FormationDQN, param_space=config,
        tune_config=tune.TuneConfig(metric="evaluation/success", mode="max", max_concurrent_trials=1),
        run_config=tune.RunConfig(stop={"training_iteration": 3}, storage_path=str(tmp_path), verbose=0))
    results = tuner.fit()
    assert not results.errors, results.errors
    assert sorted(r.config["lr"] for r in results) == sorted(LRS)
    for result in results:
        metrics = result.metrics
        assert metrics["training_iteration"] == 3
        assert 0.0 <= metrics["evaluation"]["success"] <= 1.0  # an evaluation ran: a number, not NaN
        # the learner trained with the trial's lr (read back from its optimizer)
        assert metrics["learners"]["leader"]["default_optimizer_learning_rate"] == pytest.approx(result.config["lr"])
        assert "episode_return_mean" in metrics["env_runners"]
        # every iteration reported the metric (NaN before the first evaluation)
        history = result.metrics_dataframe
        assert len(history) == 3 and "evaluation/success" in history.columns
    best = results.get_best_result()
    assert best.config["lr"] in LRS
