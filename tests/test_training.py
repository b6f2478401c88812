"""The actor-replay-learner data path on RLlib, and `formation train` with checkpoints and resume.

One small local Ray cluster (2 CPUs) serves the whole module."""

import json
import time

import pytest
import yaml

ray = pytest.importorskip("ray")

from formation.config import ConfigError  # noqa: E402
from formation.recipe.config import RunConfig  # noqa: E402

SMOKE = "configs/smoke.yaml"


def build(actors: int, teacher: dict | None = None, **train):
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load(SMOKE, {"resources.num_rollout_actors": actors,
                                 "resources.cpus_per_rollout_actor": 0.5 if actors > 1 else 1.0,
                                 **{f"train.{k}": v for k, v in train.items()},
                                 **{f"teacher.{k}": v for k, v in (teacher or {}).items()}})
    return run, build_algorithm_config(run).build_algo()


def train_until(algo, env_steps: int) -> None:
    while algo.counters["env_steps"] < env_steps:
        algo.train()


@pytest.fixture(scope="module")
def recipe_run(cluster):
    """One smoke run with every mechanism the tests below look at: 2 rollout actors, prioritized replay, the
    follower's answers to every leader move and exploring starts, trained to 3000
    env steps. What the tests read of it: the run, its counters, the replay's statistics and a sample, and the share
    of its episodes that started from an exploring start (weighed by the episodes that ended in each iteration:
    each result's shares come from those alone). The algorithm stops before the tests run, so that its actors
    leave the module's small Ray to the tests after them."""
    run, algo = build(2, teacher={"margin": 5.0, "answer_every_leader_move": True}, prioritized=True,
                      exploring_starts=0.5, learning_starts=500)
    try:
        algo.time_account()
        started, exploring, episodes = time.perf_counter(), 0.0, 0
        while algo.counters["env_steps"] < 3000:
            before = algo.counters["episodes"]
            result = algo.train()
            ended = algo.counters["episodes"] - before
            if ended:
                exploring += result["explore"]["start_exploring"] * ended
                episodes += ended
        assert episodes == algo.counters["episodes"], (episodes, algo.counters)
        seen = {"run": run, "counters": dict(algo.counters), "replay_stats": algo.replay_stats(),
                "sample": ray.get(algo.replays[0].sample.remote(256, 1, 0.97)),
                "exploring": exploring / max(episodes, 1), "episodes": episodes,
                "account": algo.time_account(), "wall": time.perf_counter() - started}
    finally:
        algo.stop()
    return seen


def test_replay_ratio_holds_and_the_driver_never_receives_transitions(recipe_run):
    run, c = recipe_run["run"], recipe_run["counters"]
    actors = run.resources.num_rollout_actors
    ratio = c["updates"] / c["env_steps"]
    assert abs(ratio - run.train.replay_ratio) <= 0.1 * run.train.replay_ratio, ratio
    stats = recipe_run["replay_stats"]
    # every env step the actors reported is in the replay, pushed by the actors themselves
    # (plus at most the samples still in flight: 2 requests per actor) ...
    in_flight = actors * 2 * run.resources.games_per_actor * run.train.steps_per_sample
    assert c["env_steps"] <= sum(s["replay_env_steps"] for s in stats) <= c["env_steps"] + in_flight
    # ... while the driver got back less than half a frame per step (a transition carries at
    # least two stacks of frames): counts, episode outcomes and learner metrics only
    frame_bytes = 9 * 9 * 4
    assert c["driver_bytes"] < 0.5 * c["env_steps"] * frame_bytes, c["driver_bytes"] / c["env_steps"]
    # the rollout actors get the learner's weights every train.weights_every_updates updates
    every = run.train.weights_every_updates
    assert c["updates"] >= 2 * every and 0 <= c["updates"] - c["weights_pushed_at"] < every, c


def test_every_kind_of_process_accounts_for_its_stages(recipe_run):
    """What benchmarks/where_time_goes.py reads: each process's seconds per stage, none more than it lived."""
    account, wall, actors = recipe_run["account"], recipe_run["wall"], recipe_run["run"].resources.num_rollout_actors
    assert {"act", "teacher", "game", "push"} <= set(account["rollout"]), account["rollout"]
    assert {"insert", "sample", "priorities"} <= set(account["replay"]), account["replay"]
    assert {"wait", "batch", "update"} <= set(account["learner"]), account["learner"]
    assert {"fetch", "learner"} <= set(account["driver"]), account["driver"]
    assert all(seconds > 0 for stages in account.values() for seconds in stages.values()), account
    assert sum(account["rollout"].values()) <= actors * wall
    for kind in ("replay", "learner", "driver"):
        assert sum(account[kind].values()) <= wall, (kind, account[kind], wall)


def test_prioritized_replay_gets_the_learners_priorities(recipe_run):
    """New records enter at the largest priority so far, 1 at the start; only priorities sent back
    by the learner (TD error, plus the weighted margin loss) can raise it."""
    assert recipe_run["counters"]["updates"] > 0
    stats = recipe_run["replay_stats"]
    assert max(s["replay_max_priority"] for s in stats) > 1.5, stats


def test_answers_to_every_leader_move_reach_the_replay_and_the_learner_learns_from_them(recipe_run):
    assert recipe_run["counters"]["updates"] > 0  # the learner took the batches with a row of labels per step
    batch = recipe_run["sample"]
    answers, labels, leader = batch["answers"], batch["labels"], batch["actions"][:, 0]
    taught = labels[:, 1] >= 0
    # the label of the move the leader played is the answer to that move ...
    assert taught.any() and (answers[taught, 1, leader[taught]] == labels[taught, 1]).all()
    # ... and the other moves have answers too
    others = (answers[:, 1] >= 0).sum(1) - taught
    assert (others >= 1).mean() > 0.5
    assert (answers[:, 0] == -1).all()


def test_exploring_starts_reach_the_rollout_actors_and_show_in_the_metrics(recipe_run):
    starts = recipe_run
    # half the episodes are exploring starts (the exact shares are tested on GameRollout itself): over the
    # 300-odd episodes the bounds are about 4 standard deviations away, and a plumbing fault (a setting that does
    # not reach the rollout actors: a share of 0) fails.
    assert starts["episodes"] >= 100, starts
    assert 0.4 < starts["exploring"] < 0.6, starts


def test_train_writes_a_checkpoint_and_resume_continues(cluster, smoke_run, tmp_path):
    import shutil

    from formation.train import read_training_record, train

    out = tmp_path / "run"
    shutil.copytree(smoke_run, out)  # `formation train configs/smoke.yaml`, as a user runs it
    summary = json.loads((out / "result.json").read_text())["greedy"]
    assert 0.0 <= summary["success"] <= 1.0 and summary["episodes"] == 50
    assert (out / "checkpoint" / "algorithm_state.pkl").is_file()
    from PIL import Image

    with Image.open(out / "greedy.gif") as gif:  # the final evaluation's first 3 episodes side by side
        assert gif.n_frames >= 2 and gif.size[0] > 3 * 84 * 4
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    first_run_steps = rows[-1]["env_steps"]
    assert first_run_steps >= 3000
    assert rows[-1]["learner/leader/lr"] == pytest.approx(1e-3)
    skipped_before = rows[-1]["faults/updates_skipped"]
    before = read_training_record(out)
    # a fine-tuning phase: a lower lr, and learning once
    # the emptied replay holds 1200 records (smoke: 500), on fewer rollout actors (a run from a cluster going on
    # on a laptop)
    train(None, str(out), resume=True, quiet=True, overrides={
        "train.total_env_steps": first_run_steps + 2000, "train.lr": 2e-4,
        "train.learning_starts": 1200, "resources.num_rollout_actors": 1, "resources.games_per_actor": 12})
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["resources"]["num_rollout_actors"] == 1 and saved["resources"]["games_per_actor"] == 12
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    resumed = rows[len(rows) - 1]
    later = [r for r in rows if r["env_steps"] > first_run_steps]
    owed = saved["train"]["replay_ratio"]  # learner updates per env step
    assert later and later[0]["learner_updates"] > 0.45 * owed * first_run_steps  # counters carried on
    # not the optimizer state's saved lr (1e-3): the resumed run's own
    assert resumed["learner/leader/lr"] == pytest.approx(2e-4)
    assert resumed["learner/follower/lr"] == pytest.approx(resumed["learner/leader/lr"])
    assert resumed["env_steps"] >= first_run_steps + 2000
    # the updates owed while the replay refilled to 1200 records were skipped, not run later
    assert resumed["faults/updates_skipped"] - skipped_before >= 0.5 * owed * 1100
    result = json.loads((out / "result.json").read_text())
    assert result["env_steps"] == resumed["env_steps"]
    # the training record (on the export's card) adds the resumed session and its wall time
    after = read_training_record(out)
    assert after["sessions"][0] == before["sessions"][0] and len(after["sessions"]) == 2
    assert after["wall_seconds"] == pytest.approx(before["wall_seconds"] + after["sessions"][1]["seconds"])
    assert after["sessions"][1]["seconds"] > 0 and after["started"] == before["started"]
    assert after["sessions"][1]["env_steps"] == [first_run_steps, resumed["env_steps"]] == [
        before["env_steps"], after["env_steps"]]
    # the replay ratio held over both runs (two actors, then one): each env step owed its share of an update,
    # run or (while the replay refilled) skipped
    ratio = (resumed["learner_updates"] + resumed["faults/updates_skipped"]) / resumed["env_steps"]
    assert abs(ratio - owed) <= 0.1 * owed, ratio


def test_resume_without_checkpoint_and_bad_config_are_one_line_errors(tmp_path):
    from formation.train import train

    with pytest.raises(ConfigError, match="no checkpoint to resume"):
        train(None, str(tmp_path / "none"), resume=True)
    run = tmp_path / "run"
    (run / "checkpoint").mkdir(parents=True)
    (run / "config.yaml").write_text("game: {}\n")
    with pytest.raises(ConfigError, match=r"^--resume: --set train\.gamma would change the run being resumed; "
                                          r"allowed: train\.learning_starts, train\.lr, "
                                          r"train\.total_env_steps, resources\.\*, refit\.\*$"):
        train(None, str(run), resume=True, overrides={"train.gamma": 0.9, "train.lr": 1e-4})
    with pytest.raises(ConfigError, match=r"^train\.gama: unknown key"):
        train(SMOKE, str(tmp_path / "bad"), overrides={"train.gama": 0.5})


def test_asking_for_more_than_the_cluster_has_fails_fast(cluster, tmp_path):
    from formation.train import train

    with pytest.raises(ConfigError, match=r"^resources\.num_gpus_per_learner: 1 GPU asked"):
        train(SMOKE, str(tmp_path / "gpu"), overrides={"resources.num_gpus_per_learner": 1})
    with pytest.raises(ConfigError, match=r"^resources\.num_rollout_actors: 8 actors"):
        train(SMOKE, str(tmp_path / "cpu"), overrides={"resources.num_rollout_actors": 8,
                                                       "resources.cpus_per_rollout_actor": 1.0})


def test_the_stock_rllib_path_trains_both_policies_on_the_papers_reward(cluster):
    import torch

    run, algo = build(1, path="stock", shaping=0.0, reward_formation_kept=None, team_reward=False, prioritized=False,
                      follower_answers_leader=False, exploration="independent", replay_ratio=0.25,
                      learning_starts=200)
    try:
        before = {m: [p.detach().clone() for p in module.parameters()] for m, module in algo.local_modules().items()}
        assert set(before) == {"leader", "follower"}
        train_until(algo, 800)
        assert algo.counters["updates"] > 0
        after = algo.local_modules()
        for m, params in before.items():
            assert any(not torch.equal(p, q) for p, q in zip(params, after[m].parameters())), m
        summary = algo.evaluate_greedy(episodes=10)
        assert summary["episodes"] == 10
    finally:
        algo.stop()


def test_the_stock_path_refuses_our_recipe_in_one_line():
    with pytest.raises(ConfigError, match=r"^train\.path: stock runs RLlib's DQN on the paper's reward alone"):
        RunConfig.load(SMOKE, {"train.path": "stock"})


def test_a_run_from_pixels_keeps_only_the_cells_in_its_replay_and_learns_from_them(cluster):
    """Where the networks read screens per cell, the replay actor holds only the cells (its bytes per record are
    those of a 9x9x3 frame, not an 84x84x3 screen), its batches are stacks of cells, and the learner updates on
    them; the rollout actors and the greedy evaluation still act on whole screens."""
    import torch

    from formation.recipe.team import replay_frame_shape
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load(SMOKE, {"game.obs_type": "pixels", "resources.num_rollout_actors": 1,
                                 "resources.cpus_per_rollout_actor": 1.0, "train.learning_starts": 200})
    assert replay_frame_shape(run) == (9, 9, 3)
    algo = build_algorithm_config(run).build_algo()
    try:
        before = {m: [p.detach().clone() for p in module.parameters()] for m, module in algo.local_modules().items()}
        train_until(algo, 800)
        assert algo.counters["updates"] > 0
        stats, = algo.replay_stats()
        assert 9 * 9 * 3 <= stats["replay_bytes_per_record"] < 9 * 9 * 3 + 100, stats
        sample = ray.get(algo.replays[0].sample.remote(8, 1, 0.97))
        assert sample["obs"].shape == sample["next_obs"].shape == (8, 9, 9, 3 * run.game.frame_stack)
        after = algo.local_modules()
        for m, params in before.items():
            assert any(not torch.equal(p, q) for p, q in zip(params, after[m].parameters())), m
        assert algo.evaluate_greedy(episodes=4)["episodes"] == 4  # acting on whole screens
    finally:
        algo.stop()


def test_data_parallel_learners_each_pull_from_their_own_shards_and_hold_equal_weights(cluster):
    """resources.num_learners: 2 runs RLlib's LearnerGroup with torch DDP (gloo on a CPU): each learner pulls half of
    train.batch_size from its own replay shard, the same number of updates per call, and after every update both
    hold the same weights (their target networks too), which differ from the weights they started from."""
    import ray
    import torch

    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load(SMOKE, {"resources.cpus_per_rollout_actor": 0.25, "resources.num_learners": 2,
                                 "resources.num_replay_shards": 2,
                                 "train.learning_starts": 200, "train.target_update_every": 5})
    config = build_algorithm_config(run)
    assert (config.num_learners, config.train_batch_size_per_learner) == (2, run.train.batch_size // 2)
    algo = config.build_algo()
    try:
        before = {m: [p.detach().clone() for p in module.parameters()] for m, module in algo.local_modules().items()}
        while algo.counters["updates"] < 2 * run.train.target_update_every:  # past two target syncs
            algo.train()
        seen = [r.get() for r in algo.learner_group.foreach_learner(
            lambda learner: (learner._shards, learner.num_updates, learner.config.train_batch_size_per_learner,
                             {m: learner.module[m].unwrapped().state_dict() for m in ("leader", "follower")}))]
        assert [s[0] for s in seen] == [[0], [1]]  # each its own shard
        assert [s[1] for s in seen] == [algo.counters["updates"]] * 2 and {s[2] for s in seen} == {16}
        (_, _, _, first), (_, _, _, second) = seen
        for m in first:
            assert any("target" in name for name in first[m])
            for name, tensor in first[m].items():
                assert torch.equal(tensor, second[m][name]), (m, name)
        after = algo.local_modules()
        for m, params in before.items():
            assert any(not torch.equal(p, q) for p, q in zip(params, after[m].parameters())), m
        # the learners sit in the placement group reserved before the rollout actors were placed (rollout actors
        # of a quarter CPU placed first could leave no node a whole CPU for a learner)
        placed = [r.get() for r in algo.learner_group.foreach_learner(
            lambda learner: ray.util.get_current_placement_group().id.hex())]
        assert placed == [algo._learners_placement.id.hex()] * 2
    finally:
        algo.stop()
    assert ray.util.placement_group_table(algo._learners_placement)["state"] == "REMOVED"  # given back



def test_a_run_that_averages_plays_and_exports_the_average_while_its_rollouts_act_with_the_networks(cluster,
                                                                                                  tmp_path):
    """``train.average_decay`` on the Ray path: the learner's modules keep the moving average of their weights after
    every update; the evaluations, the final team and a checkpoint's export are that average, and the weights sent
    to the rollout actors are the networks' own."""
    import torch

    from formation.policy import load

    run, algo = build(1, learning_starts=200, average_decay=0.9)
    try:
        while algo.counters["updates"] < 5:
            algo.train()
        [(online, averaged, pushed)] = [r.get() for r in algo.learner_group.foreach_learner(lambda learner: (
            {m: learner.module[m].unwrapped().q_network.state_dict() for m in ("leader", "follower")},
            {m: learner.module[m].unwrapped()._averaged_q_network.state_dict() for m in ("leader", "follower")},
            ray.get(learner.weights_ref()[0])))]
        team = algo.local_modules()  # what the evaluations and formation train's final team play
        exported = load(algo.save_to_path(str(tmp_path / "checkpoint")))
        for m in ("leader", "follower"):
            assert any(not torch.equal(online[m][k], averaged[m][k]) for k in online[m])  # it is another team
            for k, weight in averaged[m].items():
                assert torch.equal(team[m].q_network.state_dict()[k], weight), (m, k)
                assert torch.equal(exported.networks[m].state_dict()[k], weight), (m, k)
                assert torch.equal(torch.as_tensor(pushed[m][f"q_network.{k}"]), online[m][k]), (m, k)
            assert not any(k.startswith("_averaged") for k in pushed[m])  # the rollout actors get none of it
    finally:
        algo.stop()

def test_learners_need_shards_of_their_own_and_a_batch_that_splits():
    with pytest.raises(ConfigError, match=r"^resources\.num_replay_shards: 1 is not allowed with num_learners: 2 "
                                          r"\(each learner pulls from shards of its own\); allowed: 2 or more$"):
        RunConfig.load(SMOKE, {"resources.num_learners": 2})
    with pytest.raises(ConfigError, match=r"^train\.batch_size: 32 does not split over resources\.num_learners: 3; "
                                          r"allowed: a multiple of 3$"):
        RunConfig.load(SMOKE, {"resources.num_learners": 3, "resources.num_replay_shards": 3})
    with pytest.raises(ConfigError, match=r"^resources\.num_learners: 2 is not allowed with train\.path: stock"):
        RunConfig.load(SMOKE, {"resources.num_learners": 2, "resources.num_replay_shards": 2, "train.path": "stock"})
    with pytest.raises(ConfigError, match=r"^resources\.num_replay_shards: 3 is not allowed with num_rollout_actors: 2 "
                                          r"\(each shard is filled by actors of its own\); allowed: 1 to 2$"):
        RunConfig.load(SMOKE, {"resources.num_replay_shards": 3})
