"""Ray Tune over the algorithm as its users run it: ASHA over two trials (a grid over ``lr``) on the smoke config,
its time counted in env steps; each trial trains with its own learning rate and reports greedy success; the
experiment comes back with ``Tuner.restore``, and a trial's checkpoint loads and exports without Ray.

The grid's values are not the config's own (smoke: 1e-3), so that the learner's lr tells the grid's from the
config's. A trial costs a Tune actor, a rollout actor, the replay and the learner: the trials run one at a time."""

import json

import pytest

ray = pytest.importorskip("ray")
tune = pytest.importorskip("ray.tune")

from formation.recipe.config import RunConfig  # noqa: E402

LRS = [3e-4, 1e-4]
ENV_STEPS = "env_runners/num_env_steps_sampled_lifetime"


def test_asha_over_two_trials_on_env_steps_restores_and_a_trials_checkpoint_exports(cluster, tmp_path):
    from ray.tune.schedulers import ASHAScheduler

    from formation.cli import main
    from formation.policy import load
    from formation.rllib.algorithm import FormationDQN, build_algorithm_config

    assert RunConfig.load("configs/smoke.yaml").train.lr not in LRS  # else the trial's lr would prove nothing

    # sized for the test's Ray: the trial's process, one rollout actor and the learner; an evaluation every sample
    run = RunConfig.load("configs/smoke.yaml", {
        "resources.num_rollout_actors": 1, "resources.cpus_per_rollout_actor": 0.5, "train.learning_starts": 64,
        "eval.every_env_steps": 64, "eval.episodes": 10, "eval.gif_episodes": 0})
    config = build_algorithm_config(run).resources(num_cpus_for_main_process=0.5)
    config.training(lr=tune.grid_search(LRS))
    scheduler = ASHAScheduler(time_attr=ENV_STEPS, max_t=640, grace_period=320, reduction_factor=2)
    tuner = tune.Tuner(
        FormationDQN, param_space=config,
        tune_config=tune.TuneConfig(metric="evaluation/success", mode="max", scheduler=scheduler,
                                    max_concurrent_trials=1),
        # a trial ends at max_t env steps, once an evaluation of its own has come back
        run_config=tune.RunConfig(name="asha", stop={ENV_STEPS: 640}, storage_path=str(tmp_path), verbose=0,
                                  checkpoint_config=tune.CheckpointConfig(checkpoint_at_end=True)))
    results = tuner.fit()
    assert not results.errors, results.errors
    assert sorted(r.config["lr"] for r in results) == sorted(LRS)
    for result in results:
        metrics = result.metrics
        assert metrics["env_runners"]["num_env_steps_sampled_lifetime"] >= 320  # ASHA's grace period at least
        # the learner trained with the trial's lr (read back from its optimizer)
        assert metrics["learners"]["leader"]["default_optimizer_learning_rate"] == pytest.approx(result.config["lr"])
        assert "evaluation/success" in result.metrics_dataframe.columns  # every iteration reports it (NaN first)

    # the experiment comes back from its folder, as after a crash of the driver
    restored = tune.Tuner.restore(str(tmp_path / "asha"), trainable=FormationDQN)
    again = restored.get_results()
    assert sorted(r.config["lr"] for r in again) == sorted(LRS)
    best = again.get_best_result(metric="evaluation/success", mode="max", filter_nan_and_inf=False)
    assert best.checkpoint is not None

    # a trial's checkpoint is a team: formation.policy.load and `formation export` read it without Ray
    team = load(best.checkpoint.path)
    assert team.training["config"]["train"]["lr"] == pytest.approx(best.config["lr"])
    assert team.env_steps == best.metrics["env_runners"]["num_env_steps_sampled_lifetime"]
    out = tmp_path / "export"
    assert main(["export", best.checkpoint.path, str(out)]) == 0
    card = json.loads((out / "policy.json").read_text())
    assert card["training"]["config"]["train"]["lr"] == pytest.approx(best.config["lr"])
