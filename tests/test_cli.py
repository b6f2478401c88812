"""The ``formation`` command: the main job's GIF, one-line errors for bad input, --version and python -m formation."""

import json
import subprocess
import sys

import pytest
from PIL import Image

from formation.cli import main


def test_show_writes_a_gif_of_successful_planner_paths(tmp_path, capsys):
    assert main(["show", "--setting", "1", "--episodes", "2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert out.count("replayed: success") == 2
    gif = Image.open(tmp_path / "setting1_planner.gif")
    # two 84x84 screens scaled by 4, joined with a 2-pixel gap scaled by 4
    assert gif.size == (2 * 336 + 8, 336)
    assert gif.n_frames >= 25  # 24 planner steps on setting 1, plus the start and a held end


def test_bad_override_is_one_line_naming_the_field(capsys):
    assert main(["show", "--set", "d_min=5", "--out", "unused"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "d_min" in err and "d_max" in err


def test_unknown_key_names_the_allowed_keys(capsys):
    assert main(["show", "--set", "colour=red", "--out", "unused"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("formation: error: colour:") and "n_obstacles" in err


def test_console_script_is_installed():
    done = subprocess.run([sys.executable, "-m", "formation.cli", "show", "--setting", "7"],
                          capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip() == "formation: error: setting: unknown setting 7; allowed: 1, 2, 3, 4"


def test_version_and_python_dash_m_formation():
    import re
    from importlib.metadata import version
    from pathlib import Path

    import formation

    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    declared = re.search(r'^version = "(.+)"$', pyproject, re.MULTILINE).group(1)
    assert formation.__version__ == declared == version("formation")
    done = subprocess.run([sys.executable, "-m", "formation", "--version"], capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == f"formation {formation.__version__}"
    done = subprocess.run([sys.executable, "-m", "formation", "show", "--setting", "7"], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.strip() == "formation: error: setting: unknown setting 7; allowed: 1, 2, 3, 4"


def test_version_falls_back_to_the_source_tree_when_not_installed(monkeypatch):
    import importlib.metadata

    import formation
    from formation import cli

    def not_installed(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", not_installed)
    assert cli.version() == formation.__version__


def test_the_benchmarks_lists_of_sizes_are_whole_numbers_above_zero():
    import argparse

    from formation.cli import counts

    assert counts("1,2,4,8,14") == [1, 2, 4, 8, 14]
    for bad in ("", "0", "1,x", "2.5", "-1"):
        with pytest.raises(argparse.ArgumentTypeError, match="allowed: whole numbers above 0"):
            counts(bad)


def test_the_progress_line_that_ends_a_run_gives_its_speed(smoke_run):
    """Not "0 steps/s": the closing line has the whole run's env steps per second."""
    lines = (smoke_run.parent / "smoke-run.stdout").read_text().splitlines()
    last = [line for line in lines if "env steps" in line][-1]
    assert last.split()[-1] == "steps/s" and float(last.split()[-2].replace(",", "")) > 0, last


def test_train_no_ray_refuses_what_it_cannot_do_in_one_line(tmp_path, capsys):
    for args, words in ((["--resume"], "--resume: give the run's folder, --out DIR"),
                        (["configs/smoke.yaml", "--resume"],  # the run folder as without --resume: runs/<config>
                         "--resume: no --no-ray checkpoint to resume in 'runs/smoke'"),
                        (["configs/smoke.yaml", "--resume", "--out", str(tmp_path)],
                         "--resume: no --no-ray checkpoint to resume in"),
                        (["configs/smoke.yaml", "--out", "s3://bucket/run"],
                         "--out: 's3://bucket/run': a --no-ray run writes a local")):
        assert main(["train", "--no-ray", *args]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, err


def test_train_no_ray_leaves_a_team_that_evaluate_reads_with_how_it_was_trained(tmp_path, capsys):
    out = tmp_path / "loop"
    assert main(["train", "configs/smoke.yaml", "--no-ray", "--out", str(out), "--set", "train.total_env_steps=640",
                 "--set", "eval.every_env_steps=640", "--set", "eval.episodes=20"]) == 0
    assert "greedy success" in capsys.readouterr().out
    assert {"config.yaml", "metrics.jsonl", "result.json", "policy.json", "leader.pt", "follower.pt"} <= {
        p.name for p in out.iterdir()}
    assert main(["evaluate", str(out), "--episodes", "2", "--workers", "1"]) == 0
    trained = capsys.readouterr().out.splitlines()[1]
    assert trained.startswith("trained: 640 env steps in ") and " CPUs), " in trained, trained
    assert trained.endswith("; from the reward alone, no planner"), trained


def test_train_no_ray_stopped_by_sigterm_saves_a_checkpoint_that_resume_goes_on_from(tmp_path, capsys):
    import signal

    import torch

    out = tmp_path / "stopped"
    command = [sys.executable, "-m", "formation", "train", "configs/smoke.yaml", "--no-ray", "--out", str(out),
               "--set", "train.total_env_steps=100000000", "--set", "eval.every_env_steps=640",
               "--set", "eval.episodes=5"]
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in run.stdout:  # the first evaluation: training is under way
        if "env steps" in line:
            break
    run.send_signal(signal.SIGTERM)
    rest, _ = run.communicate(timeout=120)
    assert run.returncode == 130, rest
    saved = torch.load(out / "checkpoint.pt")
    assert saved["env_steps"] >= 640 and f"stopped at {saved['env_steps']:,} env steps: checkpoint saved" in rest
    assert "stopping once this round is saved" in rest
    assert not (out / "checkpoint.pt.partial").exists()
    total = saved["env_steps"] + 640
    assert main(["train", "--no-ray", "--resume", "--out", str(out), "--set", f"train.total_env_steps={total}"]) == 0
    assert f"resumed at {saved['env_steps']:,} env steps" in capsys.readouterr().out
    assert json.loads((out / "result.json").read_text())["env_steps"] == total
    assert main(["train", "--resume", "--out", str(out)]) == 2
    assert "holds a run trained with --no-ray; allowed: formation train --no-ray --resume" in capsys.readouterr().err
    config = (out / "config.yaml").read_text()
    for again in (["--no-ray"], []):  # a new run, with or without Ray, into the folder: refused, nothing touched
        assert main(["train", "configs/smoke.yaml", *again, "--out", str(out)]) == 2
        assert f"--out: {str(out)!r} " in capsys.readouterr().err
    assert main(["train", "--no-ray", "--resume", "--out", str(out), "--set", "train.lr=0.5"]) == 2
    assert f"the run has trained its {total:,} env steps; allowed: --set train.total_env_steps=N with N above" in \
        capsys.readouterr().err
    assert (out / "config.yaml").read_text() == config  # a refused resume changes nothing
