"""Learning, for real: the default recipe (from the reward alone) on a 9x9 board, trained by the single-process loop
(``formation.recipe.loop``, no Ray), reaches a greedy success rate that a random policy cannot, in a minute or two on
one core; the team it leaves loads with ``formation.policy.load`` and plays as it was evaluated."""

import json

import numpy as np
import pytest

from formation.evaluate import play_greedy
from formation.recipe.config import RunConfig

SMALL = "configs/small.yaml"


def test_a_random_policy_almost_never_succeeds_on_the_small_board():
    run = RunConfig.load(SMALL)
    rng = np.random.default_rng(0)
    agents = 1 + run.game.n_followers
    played = play_greedy(run.game, lambda obs: rng.integers(0, 4, size=(len(obs), agents)), 1000, run.eval.seed)
    summary = played["summary"]
    assert summary["success"] < 0.05, summary["success"]


def test_the_default_recipe_learns_the_small_board_without_ray(tmp_path):
    """configs/small.yaml measured 38.5-73.5% greedy success at 10k env steps over seeds 0-3, 47.5% with its
    own seed 0, in about a minute alone on one core; on an AMD EPYC machine 86.0 / 42.5 / 2.5 / 0.0% (seeds 0-3)."""
    from formation.policy import load
    from formation.recipe.loop import train

    run = RunConfig.load(SMALL)
    assert run.teacher is None and run.planner_options == []  # the reward alone
    out = tmp_path / "small"
    summary = train(run, out, say=lambda line: None)
    result = json.loads((out / "result.json").read_text())
    assert result["greedy"] == summary and result["env_steps"] >= run.train.total_env_steps
    assert summary["episodes"] == 200
    # a random policy succeeds in under 5% (above)
    assert summary["success"] >= 0.3, summary
    # successes take close to the shortest path (8 steps from the start row on a 9x9 board): seed 0 gave 12.4 steps
    # on one machine, under 10 on another (their float arithmetic differs, and so does the whole run)
    assert summary["steps_success_mean"] < 16, summary
    team = load(out)  # the export the loop leaves, for torch alone
    assert team.training["config"] == run.to_dict() and team.env_steps == result["env_steps"]
    again = play_greedy(team.game, team.act_batch, run.eval.episodes, run.eval.seed)["summary"]
    assert again["success"] == summary["success"]
    lines = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [row["env_steps"] for row in lines] == sorted(row["env_steps"] for row in lines)
    assert lines[-1]["greedy/success"] == summary["success"] and lines[-1]["learner_updates"] > 0
    best = load(out / "best")  # the team of the best evaluation (a tie: the later one)
    top = max(row["greedy/success"] for row in lines)
    assert best.training["evaluation"]["greedy"]["success"] == top
    assert best.env_steps == max(row["env_steps"] for row in lines if row["greedy/success"] == top)


@pytest.mark.parametrize("n_followers", [2, 3, 4])
def test_the_default_recipe_trains_teams_of_two_to_four_followers_with_one_follower_network(tmp_path, n_followers):
    """Any team size trains: the followers share one network that reads each one's role, and the team it leaves
    plays its game through PettingZoo."""
    from formation.env import parallel_env
    from formation.policy import load
    from formation.recipe.loop import train

    run = RunConfig.load(SMALL, {"game.n_followers": n_followers, "train.total_env_steps": 640,
                                 "train.learning_starts": 320, "eval.every_env_steps": 640, "eval.episodes": 10})
    out = tmp_path / f"team{n_followers}"
    train(run, out, say=lambda line: None)
    team = load(out)
    assert team.training["learner_updates"] > 0
    assert set(team.networks) == {"leader", "follower"} and team.specs["follower"].roles == n_followers
    env = parallel_env(**team.env_config)
    observations, _ = env.reset(seed=0)
    assert set(team.act(observations)) == set(env.agents) == {"leader", *(f"follower_{i}" for i in
                                                                         range(1, n_followers + 1))}


def test_one_team_trains_on_several_settings_and_team_sizes_and_plays_each(tmp_path, capfd):
    """A ``games`` section: one leader network and one follower network learn from every (setting, followers) game
    at once, their weights shared across boards, and the team plays each game as it was evaluated in training."""
    import torch

    from formation.cli import main
    from formation.policy import load

    run = RunConfig.from_dict({"game": {"obs_type": "pixels", "frame_stack": 2},
                               "games": {"settings": [1, 3], "followers": [1, 2]},
                               "train": {"total_env_steps": 1024, "learning_starts": 256, "batch_size": 16,
                                         "channels": [4, 8, 8], "hidden": 16, "replay_capacity": 4000},
                               "resources": {"games_per_actor": 4}, "eval": {"every_env_steps": 1024,
                                                                             "episodes": 4, "gif_episodes": 0}})
    out = tmp_path / "generalist"
    weights = {}
    config = tmp_path / "generalist.yaml"
    config.write_text(json.dumps(run.to_dict()))  # YAML reads JSON
    assert main(["train", str(config), "--no-ray", "--out", str(out)]) == 0
    assert "on 4 held-out scenarios of each of 4 games (their mean); run folder" in capfd.readouterr().out
    summary = json.loads((out / "result.json").read_text())["greedy"]
    names = {"setting1_followers1", "setting1_followers2", "setting3_followers1", "setting3_followers2"}
    assert set(summary["games"]) == names
    assert summary["success"] == np.mean([s["success"] for s in summary["games"].values()])
    team = load(out)
    assert team.training["learner_updates"] >= 1024 * run.train.replay_ratio
    assert team.specs["follower"].roles == 2 and team.specs["leader"].roles == 0
    row = json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])
    for name in sorted(names):
        setting, followers = int(name[7]), int(name[-1])
        game = team.for_game(setting=setting, n_followers=followers)
        played = play_greedy(game.game, game.act_batch, run.eval.episodes, run.eval.seed)["summary"]
        assert played["success"] == summary["games"][name]["success"] == row[f"greedy/{name}/success"]
        weights[name] = {m: {k: v.clone() for k, v in net.state_dict().items()} for m, net in game.networks.items()}
    # one set of weights, whatever the board
    first = weights["setting1_followers1"]
    assert all(torch.equal(first[m][k], w[m][k]) for w in weights.values() for m in w for k in w[m])
    # formation evaluate plays each of its games, and says where a game is not one of them
    assert main(["evaluate", str(out), "--setting", "3", "--followers", "2", "--episodes", "2", "--workers", "1"]) == 0
    assert "zero-shot" not in capfd.readouterr().out
    assert main(["evaluate", str(out), "--setting", "2", "--episodes", "2", "--workers", "1"]) == 0
    assert "zero-shot: playing setting 2 with 1 follower(s); trained on settings [1, 3] with [1, 2] followers" in \
        capfd.readouterr().out


def test_a_team_of_many_games_is_refused_in_one_line_where_it_cannot_train(tmp_path, capfd):
    from formation.cli import main
    from formation.config import ConfigError

    assert main(["train", "configs/generalist.yaml", "--out", str(tmp_path / "run")]) != 0  # Ray's path
    err = capfd.readouterr().err.strip().splitlines()
    assert err == ["formation: error: games: a team of many games trains in one process for now; allowed: formation "
                   "train CONFIG --no-ray"] and not (tmp_path / "run").exists()

    with pytest.raises(ConfigError, match="^games: .* allowed: no teacher$"):
        RunConfig.from_dict({"games": {"settings": [1]}, "teacher": {}})
    with pytest.raises(ConfigError, match=r"^games.followers: \[5\] is not allowed"):
        RunConfig.from_dict({"games": {"followers": [5]}})
    with pytest.raises(ConfigError, match="^games: every board is read alike only through the leader's window"):
        RunConfig.from_dict({"games": {}, "train": {"leader_window": None}})


def test_a_run_stopped_after_an_evaluation_keeps_the_team_it_evaluated(tmp_path):
    from formation.policy import load
    from formation.recipe.loop import train

    run = RunConfig.load(SMALL, {"train.total_env_steps": 1280, "train.learning_starts": 320,
                                 "eval.every_env_steps": 640, "eval.episodes": 10})
    out = tmp_path / "stopped"

    def stop(line: str) -> None:  # Ctrl-C, right after the first evaluation
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(run, out, say=stop)
    first = json.loads((out / "metrics.jsonl").read_text().splitlines()[0])
    team = load(out)
    assert team.env_steps == first["env_steps"] < run.train.total_env_steps
    assert team.training["evaluation"]["greedy"]["success"] == first["greedy/success"]
    assert not (out / "result.json").exists()


def test_a_learner_restored_from_its_state_updates_as_the_one_that_saved_it():
    """``Learner.state_dict``: networks, target copies, averages and Adam's moments; a learner loaded with it takes
    the very same next update (Adam's moments missing, or a target copy, would change it)."""
    import io

    import torch

    from formation.recipe.collect import Collector
    from formation.recipe.learn import Learner
    from formation.recipe.replay import FrameReplay
    from formation.recipe.team import network_specs, replay_frame_shape

    run = RunConfig.load(SMALL, {"train.average_decay": 0.9, "train.batch_size": 8, "train.target_update_every": 2})
    replay = FrameReplay(2000, replay_frame_shape(run), 2, run.game.frame_stack, seed=0)
    torch.manual_seed(0)
    learner = Learner(run, {m: spec.build() for m, spec in network_specs(run).items()})
    collector = Collector(run, 0)
    for _ in range(4):
        replay.add(collector.collect(learner.networks, run.train.steps_per_sample, 0)[0])
    for _ in range(3):
        learner.update(replay.sample(8, n_step=run.train.n_step, gamma=run.train.gamma))
    saved = io.BytesIO()  # through a file, as the loop's checkpoint: a state dict holds the live tensors
    torch.save(learner.state_dict(), saved)
    saved.seek(0)
    restored = Learner(run, {m: spec.build() for m, spec in network_specs(run).items()})
    restored.load_state_dict(torch.load(saved))
    sample = replay.sample(8, n_step=run.train.n_step, gamma=run.train.gamma)
    learner.update(sample)
    restored.update(sample)
    assert restored.updates == learner.updates == 4
    for part in ("networks", "targets", "averaged"):
        for m, net in getattr(learner, part).items():
            assert all(torch.equal(a, b) for a, b in zip(net.parameters(), getattr(restored, part)[m].parameters()))
    slower = Learner(RunConfig.load(SMALL, {"train.average_decay": 0.9, "train.lr": 1e-5}),
                     {m: spec.build() for m, spec in network_specs(run).items()})
    slower.load_state_dict(learner.state_dict())  # a resume that lowers the learning rate
    assert {g["lr"] for o in slower.optimizers.values() for g in o.param_groups} == {1e-5}


def test_a_resumed_run_goes_on_from_its_checkpoint_and_refills_its_replay_first(tmp_path):
    """``train(..., resume=True)``: the counters, weights and evaluations go on from ``checkpoint.pt``; the replay
    is not kept, so the updates the replay ratio owed while it refilled are skipped, as on the distributed path."""
    import torch

    from formation.policy import load
    from formation.recipe.loop import CHECKPOINT, train

    base = {"train.learning_starts": 320, "train.average_decay": 0.9, "eval.every_env_steps": 640,
            "eval.episodes": 10}
    out = tmp_path / "run"
    train(RunConfig.load(SMALL, {**base, "train.total_env_steps": 1280}), out, say=lambda line: None,
          record={"started": "first"})
    saved = torch.load(out / CHECKPOINT)
    team = load(out)
    assert saved["env_steps"] == team.env_steps == 1280
    assert saved["learner"]["updates"] == team.training["learner_updates"] > 0
    assert all(torch.equal(w.float(), saved["learner"]["averaged"][m][k])
               for m, net in team.networks.items() for k, w in net.state_dict().items())

    said = []
    train(RunConfig.load(SMALL, {**base, "train.total_env_steps": 2560}), out, say=said.append,
          record={"started": "second"}, resume=True)
    assert said[0] == f"resumed at 1,280 env steps, {saved['learner']['updates']:,} updates; the replay refills first"
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [640, 1280, 1920, 2560]
    assert rows[2]["seconds"] > rows[1]["seconds"]
    run = RunConfig.load(SMALL, base)
    owed = run.train.replay_ratio * (2560 - 1280)
    learnt = rows[3]["learner_updates"] - saved["learner"]["updates"]
    assert 0 < learnt < owed  # it learnt again once the replay held learning_starts records, not before
    assert [s["started"] for s in load(out).training["sessions"]] == ["first", "second"]


def test_the_learner_keeps_a_moving_average_of_each_networks_weights_after_every_update():
    """``train.average_decay``: after each update every averaged weight moves ``1 - decay`` of the way to the
    network's; the networks themselves learn as without it."""
    import copy

    import torch

    from formation.recipe.collect import Collector
    from formation.recipe.learn import Learner
    from formation.recipe.replay import FrameReplay
    from formation.recipe.team import network_specs, replay_frame_shape

    run = RunConfig.load(SMALL, {"train.average_decay": 0.9, "train.batch_size": 8})
    plain_run = RunConfig.load(SMALL, {"train.batch_size": 8})
    replay = FrameReplay(2000, replay_frame_shape(run), 2, run.game.frame_stack, seed=0)
    collector = Collector(run, 0)
    torch.manual_seed(0)
    networks = {m: spec.build() for m, spec in network_specs(run).items()}
    for _ in range(4):
        replay.add(collector.collect(networks, run.train.steps_per_sample, 0)[0])
    learner, plain = Learner(run, networks), Learner(plain_run, copy.deepcopy(networks))
    assert plain.averaged is None and set(learner.averaged) == set(networks)
    expected = {m: [p.detach().clone() for p in net.parameters()] for m, net in networks.items()}  # the start
    for _ in range(3):
        sample = replay.sample(8, n_step=run.train.n_step, gamma=run.train.gamma)
        learner.update(sample)
        plain.update(sample)
        for m, net in networks.items():
            expected[m] = [0.9 * e + 0.1 * p.detach() for e, p in zip(expected[m], net.parameters())]
    for m, net in networks.items():
        assert all(torch.allclose(a, e, atol=1e-6) for a, e in zip(learner.averaged[m].parameters(), expected[m]))
        assert not all(torch.equal(a, p) for a, p in zip(learner.averaged[m].parameters(), net.parameters()))
        assert all(torch.equal(a, b) for a, b in zip(net.parameters(), plain.networks[m].parameters()))


def test_a_run_that_averages_evaluates_and_exports_the_averaged_team(tmp_path):
    """The loop's evaluations, its export and ``best/`` are the averaged team's; training itself is unchanged, so
    an average that barely moves (decay near 0) leaves the very team of a run without one."""
    import torch

    from formation.policy import load
    from formation.recipe.loop import train

    base = {"train.total_env_steps": 1280, "train.learning_starts": 320, "eval.every_env_steps": 1280,
            "eval.episodes": 10}
    teams = {}
    for decay in (0.0, 1e-9, 0.99):
        out = tmp_path / f"decay{decay}"
        train(RunConfig.load(SMALL, {**base, "train.average_decay": decay}), out, say=lambda line: None)
        teams[decay] = load(out)
        assert load(out / "best").training["evaluation"] == teams[decay].training["evaluation"]
        assert teams[decay].training["config"]["train"]["average_decay"] == decay

    def weights(team):
        return [p for m in sorted(team.networks) for p in team.networks[m].state_dict().values()]

    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(weights(teams[0.0]), weights(teams[1e-9])))
    assert not all(torch.allclose(a, b, atol=1e-3) for a, b in zip(weights(teams[0.0]), weights(teams[0.99])))
    played = play_greedy(teams[0.99].game, teams[0.99].act_batch, 10, teams[0.99].eval_settings["seed"])["summary"]
    assert played["success"] == teams[0.99].training["evaluation"]["greedy"]["success"]


def test_a_bad_average_decay_and_one_rllibs_stock_dqn_would_not_keep_are_refused_in_one_line():
    from formation.config import ConfigError
    from formation.recipe.config import STOCK_TRAIN

    for bad in (1, -0.1, "0.9", True):
        with pytest.raises(ConfigError, match=r"^train\.average_decay: .* allowed: a number in \[0, 1\)"):
            RunConfig.from_dict({"train": {"average_decay": bad}})
    with pytest.raises(ConfigError, match=r"^train\.path: stock .*average_decay: 0\.0"):
        RunConfig.from_dict({"train": {**STOCK_TRAIN, "path": "stock", "average_decay": 0.999}})
