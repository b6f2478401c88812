"""Checkpoint restore for evaluation: `formation.policy.load`, `formation export`, `formation evaluate`.

One smoke run (conftest's ``smoke_run``) serves the whole module."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from formation.cli import main
from formation.config import ConfigError
from formation.env import parallel_env
from formation.evaluate import compare_with_planner, planner_paths, planner_reference, play_greedy, replay_paths
from formation.game import BatchedGame
from formation.policy import RL_MODULES, PolicyError, load
from formation.recipe.config import RunConfig

SMOKE = "configs/smoke.yaml"


@pytest.fixture(scope="module")
def run_dir(smoke_run) -> Path:
    return smoke_run


@pytest.fixture(scope="module")
def export_dir(run_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "smoke"
    assert main(["export", str(run_dir / "checkpoint"), str(out)]) == 0
    return out


def test_evaluate_is_reproducible_and_matches_trainings_final_evaluation(run_dir, tmp_path, cli):
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    done = cli("evaluate", str(run_dir), "--json", str(first), "--workers", "2")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "success" in done.stdout and "optimality gap" in done.stdout
    assert main(["evaluate", str(run_dir), "--json", str(second), "--workers", "1"]) == 0
    a, b = json.loads(first.read_text()), json.loads(second.read_text())
    assert a == b
    run = RunConfig.load(run_dir / "config.yaml")
    assert (a["episodes"], a["seed"]) == (run.eval.episodes, run.eval.seed)
    result = json.loads((run_dir / "result.json").read_text())
    assert a["env_steps"] == result["env_steps"]
    # how the team was made, for the results tables: the run's seed, env steps, wall time and hardware
    trained = a["trained"]
    assert (trained["seed"], trained["env_steps"], trained["refit_seconds"]) == (run.train.seed, a["env_steps"], None)
    assert trained["wall_seconds"] > 0 and trained["hardware"]["cpus"] >= 1
    assert trained["planner_options"] == run.planner_options
    # the same episodes as training's final greedy evaluation: every number of its summary agrees
    assert a["success"] == result["greedy"]["success"]
    for key, value in result["greedy"].items():
        assert a[key] == pytest.approx(value), key
    planner = a["planner"]
    assert planner["planner_solved"] <= a["episodes"]
    if a["success"] > 0:  # the planner's paths are the shortest: nobody succeeds faster
        assert planner["optimality_gap_mean"] >= 0
        assert a["steps_success_mean"] == pytest.approx(planner["planner_steps_on_successes_mean"]
                                                        + planner["optimality_gap_mean"])


def test_run_folder_and_export_give_the_same_actions_on_pettingzoo_observations(run_dir, export_dir):
    from_run, from_checkpoint, exported = load(run_dir), load(run_dir / "checkpoint"), load(export_dir)
    card = json.loads((export_dir / "policy.json").read_text())
    assert card["format_version"] == 1 and card["agents"] == {"leader": "leader", "follower": "follower"}
    assert card["env_steps"] == json.loads((run_dir / "result.json").read_text())["env_steps"]
    assert sorted(p.name for p in export_dir.glob("*.pt")) == ["follower.pt", "leader.pt"]
    assert exported.env_config == from_run.env_config and exported.agents == ["leader", "follower"]
    assert exported.eval_settings == from_run.eval_settings
    env = parallel_env(**exported.env_config)
    assert env.config == from_run.game  # the same game, observation type and frame stack included
    compared = 0
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        for _ in range(6):
            assert obs["leader"].shape == env.observation_space("leader").shape
            actions = from_run.act(obs)
            assert set(actions) == set(env.agents) and all(a in range(4) for a in actions.values())
            assert exported.act(obs) == actions == from_checkpoint.act(obs)
            batch = np.stack([obs["leader"]])
            assert from_run.act_batch(batch).tolist() == [[actions["leader"], actions["follower"]]]
            for module in ("leader", "follower"):
                np.testing.assert_array_equal(from_run.q_values(batch, module), exported.q_values(batch, module))
            compared += 1
            obs, _, term, trunc, _ = env.step(actions)
            if any(term.values()) or any(trunc.values()):
                break
    assert compared >= 3


def test_env_steps_come_from_the_checkpoint_even_when_result_json_is_older(run_dir, tmp_path):
    """A resumed run stopped by Ctrl-C or SIGTERM saves a checkpoint but no new result.json."""
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    trained = load(run_dir).env_steps
    assert trained == json.loads((run_dir / "result.json").read_text())["env_steps"]
    (copy / "result.json").write_text(json.dumps({"env_steps": 5, "greedy": {}}))
    assert load(copy).env_steps == trained


def test_a_half_precision_export_is_half_the_size_and_acts_alike(run_dir, export_dir, tmp_path):
    half_dir = tmp_path / "half"
    assert main(["export", str(run_dir), str(half_dir), "--half"]) == 0
    assert json.loads((half_dir / "policy.json").read_text())["weights_dtype"] == "float16"
    for module in ("leader", "follower"):
        full, half = (export_dir / f"{module}.pt").stat().st_size, (half_dir / f"{module}.pt").stat().st_size
        assert half < 0.6 * full
    exported, halved = load(export_dir), load(half_dir)
    env = parallel_env(**exported.env_config)
    screens = []
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        for _ in range(5):
            screens.append(obs["leader"])
            obs, _, term, trunc, _ = env.step(exported.act(obs))
            if any(term.values()) or any(trunc.values()):
                break
    batch = np.stack(screens)
    for module in ("leader", "follower"):
        q, q_half = exported.q_values(batch, module), halved.q_values(batch, module)
        assert q_half.dtype == q.dtype and not np.array_equal(q, q_half)  # really rounded
        np.testing.assert_allclose(q_half, q, rtol=1e-2, atol=1e-2)
    agree = (exported.act_batch(batch) == halved.act_batch(batch)).mean()
    assert agree >= 0.95, agree


def test_the_planner_replayed_has_no_optimality_gap_and_earns_the_best_return():
    config = RunConfig.load(SMOKE).game
    n, seed = 24, 1_000_000
    scenarios = play_greedy(config, lambda obs: np.full((len(obs), 2), 3), n, seed)["scenarios"]
    paths = planner_paths(config, scenarios)
    assert sum(p is not None for p in paths) >= n // 2
    played = play_greedy(config, replay_paths(paths, 2), n, seed)  # the same scenarios, from the seed
    reference = planner_reference(config, played["scenarios"], workers=2)
    assert (reference["success"] == reference["solved"]).all()
    assert (played["success"] == reference["solved"]).all()
    report = compare_with_planner(played, reference, config.agent_names)
    assert report["optimality_gap_mean"] == 0 and report["optimality_gap_max"] == 0
    assert report["return_ratio"] == {"leader": 1.0, "follower": 1.0, "team": 1.0}
    # a policy that stands still never succeeds: no gap to measure, and another return than the planner's
    still = play_greedy(config, lambda obs: np.full((len(obs), 2), 3), n, seed)
    worse = compare_with_planner(still, reference, config.agent_names)
    assert not still["success"].any() and worse["optimality_gap_mean"] is None
    assert worse["return_ratio"]["leader"] != 1.0


def _one_line_error(capfd, code: int) -> str:
    out, err = capfd.readouterr()
    assert code != 0
    assert "Traceback" not in out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_a_missing_path_or_a_folder_without_a_checkpoint_is_one_line(tmp_path, capfd):
    line = _one_line_error(capfd, main(["evaluate", str(tmp_path / "nowhere")]))
    assert "no such file or folder" in line and "nowhere" in line
    (tmp_path / "empty").mkdir()
    line = _one_line_error(capfd, main(["export", str(tmp_path / "empty"), str(tmp_path / "out")]))
    assert "is not a checkpoint" in line and "empty" in line
    with pytest.raises(PolicyError):
        load(tmp_path / "empty")


def test_a_game_the_policy_cannot_play_is_one_line_naming_the_flag(run_dir, capfd):
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--setting", "7"]))
    assert "error: --setting: " in line and "allowed: 1, 2, 3, 4" in line
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--followers", "2"]))
    assert "error: --followers: " in line and "plays 1 to 1" in line
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--followers", "0"]))
    assert "error: --followers: " in line and "n_followers" in line
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--set", "n_obstacles=99"]))
    assert "error: --set n_obstacles: 99 is not allowed; allowed: 0.." in line
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--set", "n_followers=2"]))
    assert line.endswith("error: --set n_followers: is not allowed; allowed: --followers")
    line = _one_line_error(capfd, main(["evaluate", str(run_dir), "--set", "obs_type=pixels"]))
    assert "error: --set: game.obs_type: 'pixels' is not allowed; this policy reads 'grid'" in line


def test_a_policy_that_looks_through_the_leaders_window_plays_another_board(export_dir, capfd):
    policy = load(export_dir)  # trained on a 9x9 board, it plays setting 2's 25x25 board zero-shot
    other = policy.for_game(setting=2)
    assert (other.game.setting, other.game.height, other.game.formation) == (2, 25, "vertical")
    assert other.game.obs_type == policy.game.obs_type and other.game.frame_stack == policy.game.frame_stack
    for module, net in other.networks.items():
        mine = policy.networks[module].state_dict()
        assert all(np.array_equal(v, mine[k]) for k, v in net.state_dict().items())
    env = parallel_env(**other.env_config)
    observations, _ = env.reset(seed=1)
    actions = other.act(observations)
    assert actions == dict(zip(env.agents, other.act_batch(np.stack([observations["leader"]]))[0].tolist()))
    assert set(actions.values()) <= {0, 1, 2, 3}
    # on its own game it acts as itself
    same = policy.for_game(setting=None)
    observations, _ = parallel_env(**policy.env_config).reset(seed=2)
    assert same.act(observations) == policy.act(observations)
    assert main(["evaluate", str(export_dir), "--setting", "2", "--episodes", "3", "--workers", "1"]) == 0
    out = capfd.readouterr().out
    assert "zero-shot: playing setting 2 with 1 follower(s); trained on setting None with 1" in out


def test_evaluate_plays_unseen_obstacles_with_set_and_says_so(export_dir, tmp_path, capfd):
    """Zero-shot play with more and faster obstacles than in training: ``--set`` changes the game's fields."""
    report_path = tmp_path / "faster.json"
    assert main(["evaluate", str(export_dir), "--set", "n_obstacles=4", "--set", "obstacle_speeds=[3]",
                 "--episodes", "3", "--workers", "1", "--json", str(report_path)]) == 0
    out = capfd.readouterr().out
    assert "zero-shot: playing setting None with 1 follower(s), n_obstacles=4, obstacle_speeds=[3]" in out
    report = json.loads(report_path.read_text())
    assert report["game_changes"] == {"n_obstacles": 4, "obstacle_speeds": [3]} and report["episodes"] == 3
    played = load(export_dir).for_game(load(export_dir).game.replace(n_obstacles=4, obstacle_speeds=[3])).game
    batch = BatchedGame(played, batch_size=4, seed=0)
    batch.reset()
    assert batch.obstacle_speeds.shape == (4, 4) and (batch.obstacle_speeds == 3).all()


def test_a_policy_refuses_games_its_networks_cannot_read(export_dir):
    import dataclasses

    from formation.policy import Policy

    policy = load(export_dir)
    with pytest.raises(PolicyError, match=r"^game.obs_type: 'pixels' is not allowed; this policy reads 'grid'$"):
        policy.for_game(policy.game.replace(obs_type="pixels"))
    whole = Policy(policy.game, policy.networks, {m: dataclasses.replace(s, window=None) for m, s in
                                                  policy.specs.items()}, policy.agent_modules, source="test")
    with pytest.raises(PolicyError, match="reads the whole 9x9 board"):
        whole.for_game(setting=1)


def test_a_truncated_export_module_is_one_line_and_no_traceback(export_dir, tmp_path, cli):
    bad = tmp_path / "bad"
    shutil.copytree(export_dir, bad)
    weights = (bad / "leader.pt").read_bytes()
    (bad / "leader.pt").write_bytes(weights[: len(weights) // 2])
    done = cli("evaluate", str(bad))
    assert done.returncode != 0
    assert "Traceback" not in done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "leader.pt" in lines[0] and "damaged" in lines[0], done.stderr


def test_a_truncated_checkpoint_module_or_a_foreign_card_is_one_line(run_dir, export_dir, tmp_path, capfd):
    bad_run = tmp_path / "run"
    shutil.copytree(run_dir, bad_run)
    state = bad_run / "checkpoint" / RL_MODULES / "follower" / "module_state.pkl"
    state.write_bytes(state.read_bytes()[:500])
    line = _one_line_error(capfd, main(["evaluate", str(bad_run / "checkpoint")]))
    assert "module_state.pkl" in line and "damaged" in line
    bad_card = tmp_path / "card"
    shutil.copytree(export_dir, bad_card)
    card = json.loads((bad_card / "policy.json").read_text())
    card["networks"]["leader"]["hidden"] += 1  # a card that does not describe its weights
    (bad_card / "policy.json").write_text(json.dumps(card))
    line = _one_line_error(capfd, main(["evaluate", str(bad_card)]))
    assert "leader.pt" in line and "does not fit" in line


@pytest.mark.parametrize("forecast", [False, True])
def test_an_export_of_networks_that_read_screens_per_cell_loads_them_alike(tmp_path, forecast):
    import torch

    from formation.policy import Policy, export
    from formation.recipe.team import module_of_agent, network_specs

    run = RunConfig.from_dict({"game": {"setting": 3, "obs_type": "pixels", "frame_stack": 2},
                               "train": {"screen_cells": True, "channels": [4, 8, 8], "hidden": 16,
                                         "obstacle_forecast": forecast}})
    specs, agent_modules = network_specs(run), module_of_agent(run)
    assert {spec.cells for spec in specs.values()} == {(50, 50)}
    assert {spec.build().forecast is not None for spec in specs.values()} == {forecast}
    torch.manual_seed(0)
    policy = Policy(run.game, {m: spec.build() for m, spec in specs.items()}, specs, agent_modules, source="test")
    folder = export(policy, tmp_path / "cells")
    card = json.loads((folder / "policy.json").read_text())
    assert [net["cells"] for net in card["networks"].values()] == [[50, 50]] * len(specs)
    assert [net["forecast"] for net in card["networks"].values()] == [forecast] * len(specs)
    assert not any("row_scan" in net for net in card["networks"].values())  # removed in 0.2
    again = load(folder)
    env = parallel_env(**again.env_config)
    observations, _ = env.reset(seed=7)
    for module in specs:
        obs = np.stack([observations[a] for a in observations])
        assert np.array_equal(policy.q_values(obs, module), again.q_values(obs, module))
    assert again.act(observations) == policy.act(observations)


def test_a_follower_that_answers_the_leader_acts_on_the_leaders_move_after_export(tmp_path):
    import torch

    from formation.policy import Policy, export
    from formation.recipe.team import module_of_agent, network_specs

    run = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid", "frame_stack": 2},
                               "train": {"channels": [4, 8, 8], "hidden": 16, "follower_answers_leader": True}})
    specs, agent_modules = network_specs(run), module_of_agent(run)
    assert specs["follower"].answers_leader and not specs["leader"].answers_leader
    torch.manual_seed(0)
    policy = Policy(run.game, {m: spec.build() for m, spec in specs.items()}, specs, agent_modules, source="test")
    folder = export(policy, tmp_path / "answers")
    card = json.loads((folder / "policy.json").read_text())
    assert card["networks"]["follower"]["answers_leader"] is True
    again = load(folder)
    env = parallel_env(**again.env_config)
    observations, _ = env.reset(seed=3)
    obs = np.stack([observations["leader"]])
    leader_q, follower_q = again.q_values(obs, "leader"), again.q_values(obs, "follower")
    assert follower_q.shape == (1, 16)
    leader_move = int(leader_q.argmax())
    answer = int(follower_q[0].reshape(4, 4)[leader_move].argmax())
    assert again.act(observations) == {"leader": leader_move, "follower": answer}
    assert again.act({"follower": observations["follower"]}) == {"follower": answer}  # it needs no message
    assert again.act_batch(obs).tolist() == [[leader_move, answer]]
    np.testing.assert_array_equal(again.q_batch(obs)[0, 1], follower_q[0, 4 * leader_move: 4 * leader_move + 4])


@pytest.mark.parametrize("n_followers", [2, 3, 4])
def test_followers_that_share_a_network_act_by_their_roles_through_pettingzoo_and_after_export(tmp_path, n_followers):
    import torch

    from formation.policy import Policy, export
    from formation.recipe.team import module_of_agent, network_specs

    run = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid", "frame_stack": 2,
                                        "n_followers": n_followers},
                               "train": {"channels": [4, 8, 8], "hidden": 16}})
    specs, agent_modules = network_specs(run), module_of_agent(run)
    assert specs["follower"].roles == n_followers and specs["leader"].roles == 0
    torch.manual_seed(n_followers)
    policy = Policy(run.game, {m: spec.build() for m, spec in specs.items()}, specs, agent_modules, source="test")
    again = load(export(policy, tmp_path / "team"))
    assert again.specs["follower"].roles == n_followers
    env = parallel_env(**again.env_config)
    observations, _ = env.reset(seed=5)
    for _ in range(20):
        screen = np.stack([observations["leader"]])
        q = again.q_batch(screen)[0]  # the followers read different roles of the same screen
        assert all(not np.allclose(q[i], q[j]) for i in range(1, n_followers + 1) for j in range(1, i))
        joint = again.act_batch(screen)[0]
        actions = again.act(observations)
        assert actions == dict(zip(env.agents, joint.tolist())) == policy.act(observations)
        # one follower alone acts as it does in the team (its role comes from its name)
        last = env.agents[-1]
        assert again.act({last: observations[last]}) == {last: actions[last]}
        observations, *_ = env.step(actions)
        if not env.agents:
            observations, _ = env.reset(seed=6)
    # the same networks play smaller teams, each follower by its role, and no larger one
    smaller = again.for_game(n_followers=n_followers - 1)
    observations, _ = parallel_env(**smaller.env_config).reset(seed=8)
    screen = np.stack([observations["leader"]])
    np.testing.assert_array_equal(smaller.q_batch(screen)[0], again.q_batch(screen)[0, :n_followers])
    with pytest.raises(ConfigError, match=f"plays 1 to {n_followers}$|no default start for n_followers=5"):
        again.for_game(n_followers=n_followers + 1)


def test_a_run_keeps_the_team_of_its_best_training_evaluation_which_plays_as_it_was_evaluated(run_dir):
    """`formation train` keeps in best/ the team of the training evaluation that succeeded most (a tie: the later
    one), as an export: it plays its held-out scenarios as that evaluation did."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    evaluated = {int(r["greedy/env_steps"]): r["greedy/success"] for r in rows if "greedy/env_steps" in r}
    final = json.loads((run_dir / "result.json").read_text())
    evaluated[final["env_steps"]] = final["greedy"]["success"]
    best = load(run_dir / "best")
    evaluation = best.training["evaluation"]
    top = max(evaluated.values())
    assert evaluation["greedy"]["success"] == top
    assert evaluation["env_steps"] == best.env_steps == max(s for s, v in evaluated.items() if v == top)
    assert best.training["config"] == RunConfig.load_saved(run_dir / "config.yaml").to_dict()
    # its training time up to that team, as the run's card says it (formation evaluate's `trained:` line)
    assert 0 < best.training["wall_seconds"] <= json.loads((run_dir / "training.json").read_text())["wall_seconds"]
    again = play_greedy(best.game, best.act_batch, best.eval_settings["episodes"], best.eval_settings["seed"])
    assert again["summary"]["success"] == evaluation["greedy"]["success"]


def test_the_best_team_is_replaced_only_by_one_at_least_as_good_and_never_left_half_written(export_dir, tmp_path):
    from formation.policy import BEST, best_success, keep_if_best

    def team(success: float, env_steps: int):
        policy = load(export_dir)
        policy.training = {"evaluation": {"env_steps": env_steps, "greedy": {"success": success}}}
        policy.env_steps = env_steps
        return policy

    run = tmp_path / "run"
    assert best_success(run) is None
    assert keep_if_best(team(0.5, 100), run) and best_success(run) == 0.5
    assert not keep_if_best(team(0.4, 200), run) and load(run / BEST).env_steps == 100
    assert keep_if_best(team(0.5, 300), run) and load(run / BEST).env_steps == 300  # a tie: the later team
    # stopped between the two renames: the old team is put back, and the next keeps to it
    (run / BEST).rename(run / f"{BEST}.old")
    assert best_success(run) == 0.5 and not (run / f"{BEST}.old").exists()
    assert not keep_if_best(team(0.45, 400), run) and load(run / BEST).env_steps == 300
