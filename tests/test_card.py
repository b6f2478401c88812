"""The policy card says how its team was trained (``policy.json``'s ``training`` section, from the run
folder's config.yaml, training.json and result.json), and cards from before it still load.

One smoke run (conftest's ``smoke_run``) serves the whole module; tests that change a run copy it."""

import json
import re
import shutil
from pathlib import Path

import pytest
import torch
import yaml

from formation.cli import main
from formation.policy import PolicyError, load, training_line
from formation.recipe.config import RunConfig
from formation.train import TRAINING, training_record

REPO = Path(__file__).resolve().parent.parent
COMMIT = re.compile(r"[0-9a-f]{40}(-dirty)?|unknown")


@pytest.fixture(scope="module")
def team(smoke_run, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("card") / "team"
    assert main(["export", str(smoke_run), str(out)]) == 0
    return out


def test_an_export_carries_the_run_config_counters_wall_time_hardware_commit_and_final_report(smoke_run, team):
    training = json.loads((team / "policy.json").read_text())["training"]
    assert training["config"] == yaml.safe_load((smoke_run / "config.yaml").read_text())
    result = json.loads((smoke_run / "result.json").read_text())
    assert training["env_steps"] == result["env_steps"] >= training["config"]["train"]["total_env_steps"]
    # the report the run ended with: its env steps, seed and greedy summary, as result.json has them
    assert training["evaluation"] == result
    assert training["evaluation"]["seed"] == training["config"]["eval"]["seed"]
    assert training["evaluation"]["greedy"]["episodes"] == training["config"]["eval"]["episodes"]
    record = json.loads((smoke_run / TRAINING).read_text())
    assert training["wall_seconds"] == record["wall_seconds"] > 0
    assert training["learner_updates"] == record["learner_updates"] > 0
    assert training["started"] <= training["ended"]
    assert [s["env_steps"] for s in training["sessions"]] == [[0, result["env_steps"]]]
    hardware = training["hardware"]
    assert hardware["cpus"] >= 1 and hardware["cpu"] and hardware["ray_nodes"] == 1 and hardware["ray_cpus"] >= 1
    assert hardware["torch"] == torch.__version__ and hardware["ray"] and hardware["platform"]
    assert hardware["gpu"] is None or hardware["gpus"] > 0
    assert COMMIT.fullmatch(training["commit"])
    assert load(team).training == training == load(smoke_run).training


def test_evaluate_says_in_one_line_how_the_policy_was_trained(team, capsys):
    assert main(["evaluate", str(team), "--episodes", "2", "--workers", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert re.fullmatch(r"trained: \d{1,3}(,\d{3})* env steps in \d+\.\d (min|h) on .+ \(\d+ CPUs\), "
                        r"(no GPU|.+ x\d+), 1 Ray node; commit ([0-9a-f]{12}(-dirty)?|unknown); "
                        r"from the reward alone, no planner", lines[1]), lines[1]


def test_old_cards_load_without_a_training_section_and_evaluate_as_before(capsys, tmp_path):
    old = tmp_path / "setting1"  # a card as written before the training record: no training section
    shutil.copytree(REPO / "policies" / "setting1", old)
    card = json.loads((old / "policy.json").read_text())
    card.pop("training", None)
    (old / "policy.json").write_text(json.dumps(card))
    policy = load(old)
    assert policy.training is None and "training" not in policy.card()
    assert training_line(None) is None
    assert main(["evaluate", str(old), "--episodes", "2", "--workers", "1"]) == 0
    out = capsys.readouterr().out
    assert "trained:" not in out and out.splitlines()[1].startswith("episodes")


def test_a_card_whose_training_is_not_an_object_is_refused_in_one_line(team, tmp_path):
    shutil.copytree(team, tmp_path / "team")
    card = json.loads((team / "policy.json").read_text())
    (tmp_path / "team" / "policy.json").write_text(json.dumps({**card, "training": [1]}))
    with pytest.raises(PolicyError, match=r"policy\.json' has a training section that is not a JSON object$"):
        load(tmp_path / "team")


def test_a_run_from_before_the_training_record_still_says_what_it_knows(smoke_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    (run / TRAINING).unlink()
    result = json.loads((run / "result.json").read_text())
    (run / "result.json").write_text(json.dumps({"env_steps": result["env_steps"], "greedy": result["greedy"]}))
    training = load(run).training
    assert training["config"] == yaml.safe_load((run / "config.yaml").read_text())
    assert training["evaluation"] == result  # the seed is the config's eval.seed, as training's final evaluation
    assert training["learner_updates"] > 0
    assert (training["wall_seconds"], training["hardware"], training["commit"]) == (None, None, "unknown")
    assert training_line(training) == (f"trained: {result['env_steps']:,} env steps in unrecorded time on "
                                       "unrecorded hardware; commit unknown; from the reward alone, no planner")
    taught = RunConfig.load("configs/setting1.yaml").to_dict()  # as a run saves it: every key
    assert training_line({**training, "config": taught}).endswith(
        "; the planner's labels (teacher, teacher.demonstrations, teacher.safety_horizon, refit.rounds)")


def test_a_result_older_than_the_checkpoint_is_not_its_report(smoke_run, tmp_path):
    """A resumed run stopped by Ctrl-C or SIGTERM saves a checkpoint but no new result.json."""
    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    (run / "result.json").write_text(json.dumps({"env_steps": 5, "seed": 1, "greedy": {"episodes": 1}}))
    assert load(run).training["evaluation"] is None


def test_the_record_sums_its_sessions_and_keeps_the_latest_hardware_and_commit():
    first = {"started": "a", "ended": "b", "seconds": 10.0, "env_steps": [0, 100], "commit": "x",
             "hardware": {"cpus": 2}}
    record = training_record(None, first, {"env_steps": 100, "updates": 7})
    assert (record["wall_seconds"], record["env_steps"], record["learner_updates"]) == (10.0, 100, 7)
    second = {"started": "c", "ended": "d", "seconds": 5.5, "env_steps": [100, 300], "commit": "y",
              "hardware": {"cpus": 16}}
    record = training_record(record, second, {"env_steps": 300, "updates": 20})
    assert (record["wall_seconds"], record["started"], record["ended"]) == (15.5, "a", "d")
    assert (record["commit"], record["hardware"], record["sessions"]) == ("y", {"cpus": 16}, [first, second])
    line = training_line({"env_steps": 300, "wall_seconds": 2 * 3600, "sessions": record["sessions"],
                          "hardware": {"cpu": "Xeon", "cpus": 16, "gpu": "H100", "gpus": 1.0, "ray_nodes": 2},
                          "commit": "0123456789abcdef0123456789abcdef01234567-dirty"})
    assert line == "trained: 300 env steps in 2.0 h on Xeon (16 CPUs), H100 x1, 2 Ray nodes; commit 0123456789ab-dirty"


def test_a_refit_keeps_the_training_section_and_adds_its_own(smoke_run, tmp_path, monkeypatch):
    import formation.recipe.safety_refit as safety_refit

    monkeypatch.setattr(safety_refit, "check_refittable", lambda policy, name=None: None)
    monkeypatch.setattr(safety_refit, "refit", lambda policy, settings, say, keep=None: {"rounds": [], "seconds": 1.0})
    assert main(["refit", str(smoke_run), str(tmp_path / "refitted"), "--set", "refit.rounds=1"]) == 0
    card = json.loads((tmp_path / "refitted" / "policy.json").read_text())
    assert card["training"] == load(smoke_run).training
    assert COMMIT.fullmatch(card["refit"]["commit"]) and card["refit"]["hardware"]["cpus"] >= 1
    assert card["refit"]["started"] <= card["refit"]["ended"] and card["refit"]["seconds"] == 1.0
    # an evaluation report counts every refit's time after training's (a refit of a refit: both)
    from formation.policy import how_trained

    refitted = load(tmp_path / "refitted")
    refitted.refit_report = {"seconds": 2.0, "earlier": refitted.refit_report}
    trained = how_trained(refitted)
    assert trained["refit_seconds"] == 3.0 and trained["wall_seconds"] == card["training"]["wall_seconds"]
    # the refit's labels come from the planner, whether or not training's own config had a refit phase
    before = RunConfig.from_saved(card["training"]["config"]).planner_options
    assert "refit.rounds" not in before and trained["planner_options"] == [*before, "refit.rounds"]
    refitted.training = {**refitted.training, "config": {"train": {"gamma": "high"}}}
    assert how_trained(refitted)["planner_options"] is None  # a card whose run config does not load
