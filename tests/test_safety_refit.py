"""``formation refit``: a trained team's safety heads fitted again on fresh states of its own play, labelled by
the planner, while the Q-values stay as trained; the refitted team is written as an export."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest
import torch

from formation.cli import main
from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame, Observer
from formation.planner import surviving_first_moves_many
from formation.policy import Policy, export, load
from formation.recipe.config import RefitSettings, RunConfig
from formation.recipe.qnet import NetworkSpec
from formation.recipe.safety_refit import StateBank, label_states, refit, safety_parameters

SMOKE = "configs/smoke.yaml"
GRID = GameConfig.from_setting(2, obs_type="grid", frame_stack=2, height=9, width=9, n_obstacles=2)


def grid_team(safety_encoder: bool = True, safety: bool = True) -> Policy:
    """A team of small untrained networks with safety heads on the 9x9 grid game."""
    spec = NetworkSpec(obs_shape=(9, 9, 8), high=1.0, hidden=32, channels=(8, 16, 16), window=(8, 1, 8),
                       forecast=True, safety=safety, safety_encoder=safety_encoder)
    follower = NetworkSpec(**{**spec.__dict__, "answers_leader": True})
    torch.manual_seed(0)
    return Policy(GRID, {"leader": spec.build(), "follower": follower.build()}, {"leader": spec, "follower": follower},
                  ["leader", "follower"], "test")


def screens_of_grid(games: int = 16) -> np.ndarray:
    game = BatchedGame(GRID, batch_size=games, seed=1)
    game.reset()
    return Observer(game).observe(np.ones(games, bool))


def screens(setting: int, games: int = 16, steps: int = 5) -> np.ndarray:
    game = BatchedGame(GameConfig.from_setting(setting), batch_size=games, seed=1)
    game.reset()
    observer = Observer(game)
    obs = observer.observe(np.ones(games, bool))
    rng = np.random.default_rng(0)
    for _ in range(steps):
        game.step(rng.integers(0, 4, (games, 2)))
        obs = observer.observe(game.done)
    return obs


@pytest.mark.parametrize("key,value,message", [
    ("rounds", -1, "refit.rounds: -1 is not allowed; allowed: an integer >= 0"),
    ("epsilon", 1.5, "refit.epsilon: 1.5 is not allowed; allowed: a number in [0.0, 1.0]"),
    ("horizon", "far", "refit.horizon: 'far' is not allowed; allowed: an integer >= 1"),
    ("epochs", 0, "refit.epochs: 0 is not allowed; allowed: a number in (0.0, 1000.0]"),
    ("veto_fallback", "all", "refit.veto_fallback: 'all' is not allowed; allowed: above_half, most_probable"),
])
def test_a_bad_refit_setting_is_one_line(key, value, message):
    with pytest.raises(ConfigError) as err:
        RunConfig.load(SMOKE, {f"refit.{key}": value})
    assert str(err.value) == message


def test_a_refit_phase_is_off_unless_the_config_names_one_and_needs_one_follower():
    assert RunConfig.load(SMOKE).refit.rounds == 0
    with pytest.raises(ConfigError) as err:
        RunConfig.load(SMOKE, {"game.n_followers": 2, "refit.rounds": 1})
    assert str(err.value) == "refit.rounds: 1 needs game.n_followers: 1 (not 2); allowed: 0"


def test_heads_added_to_a_team_without_them_start_from_its_encoders_and_leave_its_moves_alone():
    from formation.recipe.safety_refit import add_safety_heads

    team = grid_team(safety=False, safety_encoder=False)
    obs = screens_of_grid()
    before = team.act_batch(obs)
    weights = {m: {k: v.clone() for k, v in net.state_dict().items()} for m, net in team.networks.items()}
    assert add_safety_heads(team) == ["follower", "leader"] and not team.learned_veto
    for module, net in team.networks.items():
        assert team.specs[module].safety and team.specs[module].safety_encoder and net.spec == team.specs[module]
        state = net.state_dict()
        assert all(torch.equal(state[k], v) for k, v in weights[module].items())  # every trained weight kept
        copied = net.safety_encoder[0].state_dict()
        assert all(torch.equal(v, net.encoder.state_dict()[k]) for k, v in copied.items())
    assert (team.act_batch(obs) == before).all()  # no veto until the heads are fitted
    assert add_safety_heads(team) == []  # a team with heads keeps them


def test_training_fits_the_safety_heads_through_ray_and_ends_with_the_refit_phase_its_config_names(cluster, tmp_path):
    """The settings' path in small: the learner fits safety heads on their own encoders beside the Q-values, then
    the refit phase fits them again on fresh play; the Q-values stay as trained."""
    from formation.policy import REFITTED
    from formation.recipe.rollout import GameRollout
    from formation.train import refit_phase, train

    out = tmp_path / "run"
    summary = train(SMOKE, str(out), quiet=True, overrides={
        "teacher.safety_horizon": 2, "teacher.safety_encoder": True, "train.total_env_steps": 2000,
        "eval.every_env_steps": 2000, "refit.rounds": 1, "refit.episodes": 30, "refit.horizon": 2,
        "refit.holdout_episodes": 10, "refit.workers": 1})
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert any("learner/follower/safety_error" in row for row in rows)
    team, trained = load(out), load(out / "checkpoint")  # the run's final team; the networks as trained
    assert trained.learned_veto and all(net.safety is not None for net in trained.networks.values())
    # on states of fresh games, the trained heads' verdicts beat the best constant guess of each joint move
    rollout = GameRollout(trained.game, 64, seed=99)
    rng = np.random.default_rng(0)
    wrong, truth = [], []
    for _ in range(8):
        safe = surviving_first_moves_many([rollout.game.scenario(i) for i in range(64)], config=trained.game,
                                          horizon=2)
        bits = ((safe[:, None] >> np.arange(16, dtype=np.uint64)) & np.uint64(1)).astype(bool)
        wrong.append(trained.learned_safe_moves(rollout.observations).reshape(64, 16) != bits)
        truth.append(bits)
        rollout.step(rng.choice([0, 0, 1, 2, 3], size=(64, 2)))
    truth = np.concatenate(truth)
    constant = np.minimum(truth.mean(0), 1 - truth.mean(0)).mean()
    assert np.concatenate(wrong).mean() < 0.9 * constant, (np.concatenate(wrong).mean(), constant)

    report = team.refit_report
    assert report["evaluation"] == {"seed": 1_000_000, "greedy": summary}
    assert report["settings"]["episodes"] == 30 and report["seconds"] > 0 and report["hardware"]
    assert report["heads_added"] == [] and team.learned_veto
    assert (team.veto_threshold, trained.refit_report) == (0.97, None)
    assert team.training["config"]["refit"]["rounds"] == 1 and team.training["wall_seconds"] > 0
    for module, net in team.networks.items():  # the heads fitted again, the Q-values kept as trained
        before, after = trained.networks[module].state_dict(), net.state_dict()
        refitted = {k for k in after if not torch.equal(before[k], after[k])}
        assert refitted and all(k.startswith(("safety.", "safety_encoder.")) for k in refitted), refitted
    # a refit again (a --resume after more training does one) replaces the team whole
    refit_phase(out, RunConfig.load_saved(out / "config.yaml", {"refit.episodes": 20}), say=lambda line: None)
    assert load(out).refit_report["settings"]["episodes"] == 20
    assert [p.name for p in out.iterdir() if p.name.startswith((REFITTED, "refit."))] == [REFITTED]


@pytest.mark.parametrize("seed,bad", [(2_000_000, True), (1_999_996, True), (2_000_001, True), (1_999_995, False),
                                      (2_000_002, False), (10_000_000, False)])
def test_a_refit_never_plays_the_evaluations_scenarios(seed, bad):
    # 5 rounds of 1000 games take seeds seed..seed+4, the 300 held-out games seed-1: none may be 2e6 (the test set)
    overrides = {"refit.seed": seed, "refit.rounds": 5, "refit.episodes": 1000, "teacher.safety_horizon": 4}
    if bad:
        with pytest.raises(ConfigError, match=rf"^refit\.seed: {seed} is not allowed; its games would use seeds "
                                              rf"{seed - 1}\.\.{seed + 4}, which hold the evaluations' scenarios"):
            RunConfig.load(SMOKE, overrides)
    else:
        assert RunConfig.load(SMOKE, overrides).refit.seed == seed


def test_states_are_kept_a_bit_an_entry_and_read_back_as_the_network_prepares_them():
    for setting in (2, 4):
        obs, config = screens(setting), GameConfig.from_setting(setting)
        net = NetworkSpec(obs_shape=obs.shape[1:], high=255.0, hidden=16, channels=(4, 8, 8), window=(12, 3, 10),
                          frame_channels=3, cells=(config.height, config.width), forecast=True,
                          safety=True, safety_encoder=True).build()
        prepared = net.prepare(torch.from_numpy(obs))
        bank = StateBank()
        bank.add(prepared[:10])
        bank.add(prepared[10:])
        assert len(bank) == len(obs)
        assert bank.nbytes == len(obs) * -(-prepared[0].numel() // 8)  # a bit an entry, rounded up to bytes
        got = bank.batch(np.arange(len(obs)))
        assert got.shape == prepared.shape and got.is_contiguous(memory_format=torch.channels_last)
        assert torch.allclose(got, prepared, atol=1e-6) and got.sum() > 0
        assert torch.allclose(bank.batch(np.array([3, 0])), prepared[[3, 0]], atol=1e-6)
    with pytest.raises(ValueError, match="entries other than 0 and 1"):
        StateBank().add(torch.full((1, 2, 3, 3), 0.5))


def test_labels_are_the_planners_safe_joint_moves_bit_by_bit():
    game = BatchedGame(GRID, batch_size=300, seed=2)
    game.reset()
    game.step(np.zeros((300, 2), int))
    scenarios = [game.scenario(i) for i in np.flatnonzero(~game.done)]
    labels = label_states(scenarios, GRID, horizon=3)
    masks = surviving_first_moves_many(scenarios, config=GRID, horizon=3)
    assert labels.shape == (len(scenarios), 16)
    for row, mask in zip(labels, masks):
        assert [bool(int(mask) >> j & 1) for j in range(16)] == row.tolist()
    assert labels.any() and not labels.all()


def test_refit_cuts_the_heads_wrong_verdicts_and_leaves_the_q_values_alone():
    policy = grid_team()
    before = {m: {k: v.clone() for k, v in net.state_dict().items()} for m, net in policy.networks.items()}
    trained = {m: {n for part in safety_parameters(net) for n, _ in part.named_parameters()}
               for m, net in policy.networks.items()}
    settings = RefitSettings(rounds=2, episodes=300, horizon=2, epochs=8.0, lr=3e-3, batch_size=128,
                             holdout_episodes=150, epsilon=0.2, workers=1)
    lines: list[str] = []
    report = refit(policy, settings, say=lines.append)
    held = report["holdout"]
    wrong_before = held["before"]["unsafe_judged_safe"] + held["before"]["safe_judged_unsafe"]
    after = report["rounds"][-1]["holdout"]
    wrong_after = after["unsafe_judged_safe"] + after["safe_judged_unsafe"]
    verdicts = after["safe"] + after["unsafe"]
    assert verdicts == 16 * held["states"] > 1000
    # an untrained head is wrong about as often as not; refitted, far less often
    assert wrong_before > 0.25 * verdicts and wrong_after < 0.5 * wrong_before
    assert len(report["rounds"]) == 2 and report["rounds"][1]["states_in_all"] > report["rounds"][0]["states"]
    assert any(line.startswith("round 2/2 done") for line in lines)
    for module, net in policy.networks.items():
        for name, value in net.state_dict().items():
            learnt = name.startswith(("safety.", "safety_encoder."))
            assert torch.equal(value, before[module][name]) != learnt, name
        assert all(not p.requires_grad for p in net.parameters()) and not net.training
        assert {n for n in trained[module]} == {n for n, _ in net.safety.named_parameters()} | \
            {n for n, _ in net.safety_encoder.named_parameters()}


def test_a_refit_stopped_after_a_round_goes_on_from_it_to_the_same_heads(tmp_path):
    settings = RefitSettings(rounds=2, episodes=60, horizon=2, holdout_episodes=30, epsilon=0.2, workers=1)
    whole = grid_team()
    report = refit(whole, settings, say=lambda _: None)

    def stop_after_round_1(line: str) -> None:
        if line.startswith("round 1/2 done"):
            raise KeyboardInterrupt  # Ctrl-C, or a session's end, between rounds
    keep = tmp_path / "rounds"
    with pytest.raises(KeyboardInterrupt):
        refit(grid_team(), settings, say=stop_after_round_1, keep=keep)
    lines: list[str] = []
    resumed = grid_team()  # the trained team loaded again, as --resume does
    again = refit(resumed, settings, say=lines.append, keep=keep)
    assert lines[0].startswith("refit: round(s) 1-1 kept in")
    assert not any(line.startswith("round 1/2") for line in lines)  # round 1 was not played again
    assert [r["states_in_all"] for r in again["rounds"]] == [r["states_in_all"] for r in report["rounds"]]
    assert again["rounds"][1]["holdout"] == report["rounds"][1]["holdout"] and again["holdout"] == report["holdout"]
    for module, net in resumed.networks.items():
        for name, value in net.state_dict().items():
            assert torch.equal(value, whole.networks[module].state_dict()[name]), name
    assert [p.name for p in keep.iterdir()] == ["round2"]
    fewer = dataclasses.replace(settings, episodes=50)
    lines.clear()  # rounds kept are no start for a refit with other settings
    refit(grid_team(), fewer, say=lines.append, keep=keep)
    assert lines[0] == f"refit: the round(s) kept in {keep} were made with other settings or for another team; " \
        "starting over"
    other = grid_team()  # nor for another team, such as the same run trained further
    with torch.no_grad():
        other.networks["leader"].value[0].weight[0, 0] += 1
    lines.clear()
    refit(other, fewer, say=lines.append, keep=keep)
    assert lines[0].endswith("were made with other settings or for another team; starting over")
    (keep / "round2" / "bank.npy").write_bytes(b"cut short")  # a disk that lost a file: start over, in one line
    lines.clear()
    refit(other, fewer, say=lines.append, keep=keep)
    assert lines[0].startswith(f"refit: the round(s) kept in {keep} could not be read (") \
        and lines[0].endswith("); starting over")


def test_a_head_on_the_q_values_features_refits_alone():
    policy = grid_team(safety_encoder=False)
    encoder = {m: net.encoder[0].weight.clone() for m, net in policy.networks.items()}
    head = {m: net.safety[0].weight.clone() for m, net in policy.networks.items()}
    refit(policy, RefitSettings(rounds=1, episodes=50, horizon=2, holdout_episodes=0, workers=1), say=lambda _: None)
    for m, net in policy.networks.items():
        assert torch.equal(net.encoder[0].weight, encoder[m]) and not torch.equal(net.safety[0].weight, head[m])


def test_the_refit_travels_with_the_export(tmp_path):
    policy = grid_team()
    report = refit(policy, RefitSettings(rounds=1, episodes=60, horizon=2, holdout_episodes=30, workers=1),
                   say=lambda _: None)
    policy.refit_report = report
    reloaded = load(export(policy, tmp_path / "out"))
    card = json.loads((tmp_path / "out" / "policy.json").read_text())
    assert card["refit"]["settings"]["horizon"] == 2 and card["refit"]["rounds"][0]["states"] > 0
    assert reloaded.refit_report == card["refit"]
    game = BatchedGame(GRID, batch_size=8, seed=0)
    game.reset()
    obs = Observer(game).observe(np.ones(8, bool))
    assert (reloaded.learned_safe_moves(obs) == policy.learned_safe_moves(obs)).all()


def test_the_command_refits_an_export_into_a_new_folder(tmp_path, capsys):
    export(grid_team(), tmp_path / "team")
    args = ["refit", str(tmp_path / "team"), str(tmp_path / "refitted"), "--set", "refit.rounds=1",
            "--set", "refit.episodes=40", "--set", "refit.horizon=2", "--set", "refit.holdout_episodes=20",
            "--set", "refit.workers=1"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "round 1/1 done" in out and "wrote" in out
    assert load(tmp_path / "refitted").refit_report["settings"]["episodes"] == 40
    assert not (tmp_path / "refitted.partial").exists()
    # the folder now holds a policy: a second refit into it is refused before any work
    assert main(args) == 2
    assert re.search(r"not (an )?empty", capsys.readouterr().err)  # nothing is overwritten
    # a refit of the refitted team keeps the first refit's report on its card
    again = ["refit", str(tmp_path / "refitted"), str(tmp_path / "again"), *args[3:]]
    again[again.index("refit.episodes=40")] = "refit.episodes=30"
    assert main(again) == 0
    report = load(tmp_path / "again").refit_report
    assert report["settings"]["episodes"] == 30 and report["earlier"]["settings"]["episodes"] == 40
    assert "earlier" not in report["earlier"]


@pytest.mark.parametrize("setting,message", [
    ("train.lr=0.1", "--set train.lr: refit takes refit.* keys only"),
    ("refit.speed=2", "refit.speed: unknown key; allowed: batch_size, episodes, epochs"),
    ("refit.episodes=-3", "refit.episodes: -3 is not allowed; allowed: an integer >= 1"),
    ("refit.epochs=2", "names no refit phase); allowed: --set refit.rounds=N with N >= 1"),
])
def test_the_commands_bad_input_is_one_line(tmp_path, capsys, setting, message):
    export(grid_team(), tmp_path / "team")
    assert main(["refit", str(tmp_path / "team"), str(tmp_path / "out"), "--set", setting]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err
    assert not (tmp_path / "out").exists()


def test_the_command_gives_a_team_without_safety_heads_fitted_ones_and_a_missing_team_is_one_line(tmp_path, capsys):
    export(grid_team(safety=False, safety_encoder=False), tmp_path / "plain")
    args = ["--set", "refit.rounds=2", "--set", "refit.episodes=20", "--set", "refit.horizon=2",
            "--set", "refit.holdout_episodes=10", "--set", "refit.workers=1"]
    assert main(["refit", str(tmp_path / "plain"), str(tmp_path / "out"), *args]) == 0
    assert "safety heads added to follower, leader" in capsys.readouterr().out
    card = json.loads((tmp_path / "out" / "policy.json").read_text())
    assert all(spec["safety"] and spec["safety_encoder"] for spec in card["networks"].values())
    assert load(tmp_path / "out").learned_veto
    assert main(["refit", str(tmp_path / "nothing"), str(tmp_path / "out2")]) == 2
    assert "checkpoint: no such file or folder" in capsys.readouterr().err
    assert not (tmp_path / "out2").exists()


def test_the_command_takes_its_settings_from_a_run_folders_refit_section(tmp_path, capsys):
    import pickle

    import yaml

    from formation.policy import RL_MODULES
    from formation.recipe.team import network_specs

    run = RunConfig.load(SMOKE, {"teacher.safety_horizon": 2, "teacher.safety_encoder": True, "refit.rounds": 1,
                                 "refit.episodes": 30, "refit.horizon": 2, "refit.holdout_episodes": 10,
                                 "refit.workers": 1})
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "config.yaml").write_text(yaml.safe_dump(run.to_dict()))
    specs = network_specs(run)
    torch.manual_seed(0)
    for module, spec in specs.items():  # a checkpoint's module state, as RLlib saves it
        state = {f"q_network.{k}": v.numpy() for k, v in spec.build().state_dict().items()}
        (folder / "checkpoint" / RL_MODULES / module).mkdir(parents=True)
        with (folder / "checkpoint" / RL_MODULES / module / "module_state.pkl").open("wb") as f:
            pickle.dump(state, f)
    assert main(["refit", str(folder), str(tmp_path / "out"), "--set", "refit.epochs=2"]) == 0
    assert "1 round(s) of 30 games, labels over 2 steps" in capsys.readouterr().out
    settings = load(tmp_path / "out").refit_report["settings"]
    assert (settings["episodes"], settings["horizon"], settings["epochs"]) == (30, 2, 2.0)
    assert load(tmp_path / "out").veto_threshold == settings["veto_threshold"] == 0.97
    assert load(tmp_path / "out").veto_fallback == settings["veto_fallback"] == "most_probable"


def test_the_veto_keeps_to_moves_above_its_threshold_and_falls_back_to_one_half():
    from formation.policy import within_veto

    p = np.zeros((3, 4, 4))
    p[0, 0, 0], p[0, 1, 1], p[0, 2, 2] = 0.99, 0.7, 0.3  # one move above 0.9
    p[1, 0, 1], p[1, 3, 3] = 0.8, 0.6  # none above 0.9, two above one half
    p[2] = 0.2  # none above one half: greedy_within then keeps to all moves
    assert np.array_equal(within_veto(p, 0.5), p > 0.5)
    strict = within_veto(p, 0.9)
    assert strict[0].sum() == 1 and strict[0, 0, 0]
    assert np.array_equal(strict[1], p[1] > 0.5) and not strict[2].any()
    assert np.array_equal(within_veto(p, 0.1), p > 0.1)
    assert np.array_equal(within_veto(p, 0.9, "above_half"), strict)


def test_the_veto_can_fall_back_to_the_most_probably_safe_moves_instead():
    from formation.policy import within_veto

    p = np.zeros((3, 4, 4))
    p[0, 0, 0], p[0, 1, 1], p[0, 2, 2] = 0.99, 0.98, 0.3  # two moves above 0.97: both kept, as before
    p[1, 0, 1], p[1, 3, 3], p[1, 2, 0] = 0.8, 0.96, 0.6  # none above 0.97: the likeliest alone, not all above 1/2
    p[2] = 0.2
    p[2, 1, 2] = 0.25  # none above one half either: still the likeliest, not every move
    kept = within_veto(p, 0.97, "most_probable")
    assert np.array_equal(kept[0], p[0] > 0.97)
    assert kept[1].sum() == 1 and kept[1, 3, 3]
    assert kept[2].sum() == 1 and kept[2, 1, 2]
    assert within_veto(np.full((1, 4, 4), 0.4), 0.97, "most_probable").all()  # ties: all of them
    with pytest.raises(ValueError, match="fallback: 'all' is not allowed"):
        within_veto(p, 0.97, "all")


def test_the_veto_fallback_travels_with_the_export_and_bad_ones_are_one_line(tmp_path, capsys):
    assert grid_team().veto_fallback == "above_half"
    reloaded = load(export(grid_team().with_veto_threshold(0.9).with_veto_fallback("most_probable"), tmp_path / "team"))
    assert reloaded.veto_fallback == "most_probable"
    game = BatchedGame(GRID, batch_size=32, seed=4)
    game.reset()
    obs = Observer(game).observe(np.ones(32, bool))
    moves, (_, p) = reloaded.act_batch(obs), reloaded.outputs(obs)
    chosen = p[np.arange(32), moves[:, 0], moves[:, 1]]
    none_above = ~(p > reloaded.veto_threshold).any(axis=(1, 2))
    assert none_above.any()
    assert np.allclose(chosen[none_above], p[none_above].max(axis=(1, 2)))  # where none is above: the likeliest
    card_file = tmp_path / "team" / "policy.json"
    card = json.loads(card_file.read_text())
    assert card["veto_fallback"] == "most_probable"
    card_file.write_text(json.dumps({k: v for k, v in card.items() if k != "veto_fallback"}))
    assert load(tmp_path / "team").veto_fallback == "above_half"  # cards from before the choice
    card_file.write_text(json.dumps({**card, "veto_fallback": "all"}))
    with pytest.raises(ConfigError, match="has veto_fallback 'all'; allowed: above_half, most_probable$"):
        load(tmp_path / "team")
    export(grid_team(), tmp_path / "fine")
    assert main(["export", str(tmp_path / "fine"), str(tmp_path / "out"), "--veto-fallback", "most_probable"]) == 0
    assert load(tmp_path / "out").veto_fallback == "most_probable"
    report = tmp_path / "report.json"
    assert main(["evaluate", str(tmp_path / "out"), "--episodes", "8", "--workers", "1", "--veto-fallback",
                 "above_half", "--json", str(report)]) == 0
    assert json.loads(report.read_text())["veto_fallback"] == "above_half"
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["evaluate", str(tmp_path / "out"), "--veto-fallback", "all"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--veto-fallback: invalid choice: 'all'" in err and "'most_probable'" in err


def test_the_veto_threshold_travels_with_the_export_and_bad_ones_are_one_line(tmp_path, capsys):
    policy = grid_team().with_veto_threshold(0.9)
    assert grid_team().veto_threshold == 0.5
    reloaded = load(export(policy, tmp_path / "team"))
    assert reloaded.veto_threshold == 0.9
    game = BatchedGame(GRID, batch_size=32, seed=4)
    game.reset()
    obs = Observer(game).observe(np.ones(32, bool))
    moves = reloaded.act_batch(obs)
    kept = reloaded.learned_safe_moves(obs)
    played = kept[np.arange(32), moves[:, 0], moves[:, 1]]
    assert played[kept.any(axis=(1, 2))].all()
    card = json.loads((tmp_path / "team" / "policy.json").read_text())
    (tmp_path / "team" / "policy.json").write_text(json.dumps({**card, "veto_threshold": 1.5}))
    with pytest.raises(ConfigError, match="has veto_threshold 1.5; allowed: a number in"):
        load(tmp_path / "team")
    assert main(["evaluate", str(tmp_path / "nowhere"), "--veto-threshold", "1.2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "checkpoint: no such file" in err
    export(grid_team(), tmp_path / "fine")
    assert main(["evaluate", str(tmp_path / "fine"), "--veto-threshold", "1.2"]) == 2
    assert "--veto-threshold: 1.2 is not allowed; allowed: a number in [0, 1)" in capsys.readouterr().err


def test_an_export_can_set_the_veto_threshold_and_keeps_the_refit_report(tmp_path, capsys):
    policy = grid_team()
    policy.refit_report = {"settings": {"horizon": 2}, "rounds": []}
    export(policy, tmp_path / "team")
    assert main(["export", str(tmp_path / "team"), str(tmp_path / "strict"), "--veto-threshold", "0.9"]) == 0
    strict = load(tmp_path / "strict")
    assert strict.veto_threshold == 0.9 and strict.refit_report == policy.refit_report
    assert main(["export", str(tmp_path / "team"), str(tmp_path / "bad"), "--veto-threshold", "-0.1"]) == 2
    assert "--veto-threshold: -0.1 is not allowed" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
