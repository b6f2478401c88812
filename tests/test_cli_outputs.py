"""Nothing overwritten, every error one line: each command's output missing, unwritable, existing or
inside its own source (issue 38, part 9). No training: the shipped policies, copied, and a few episodes."""

import errno
import json
import shutil
from pathlib import Path

import pytest

from formation.cli import main

POLICIES = Path(__file__).resolve().parents[1] / "policies"
UNWRITABLE = "/proc/formation-test/out"  # /proc takes no new folders, not even from root


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def one_line_error(capfd, code: int, *words: str) -> str:
    out, err = capfd.readouterr()
    assert code != 0 and "Traceback" not in out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("formation: error: "), lines[0]
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


@pytest.fixture
def team(tmp_path) -> Path:
    """A copy of the shipped setting-1 policy, so that a bug here cannot touch policies/."""
    return Path(shutil.copytree(POLICIES / "setting1", tmp_path / "team"))


def no_leftovers(folder: Path) -> bool:
    """Nothing half-written: no temporary folder or file beside the outputs."""
    return not [p for p in folder.rglob(".*") if ".writing-" in p.name or ".formation-probe-" in p.name]


# ---------------------------------------------------------------------- export
def test_export_refuses_a_folder_that_holds_an_export_and_keeps_it_whole(tmp_path, capfd):
    first = tmp_path / "first"
    assert main(["export", str(POLICIES / "setting2"), str(first)]) == 0
    kept = snapshot(first)
    line = one_line_error(capfd, main(["export", str(POLICIES / "setting1"), str(first)]), "dir:", str(first),
                          "not empty", "nothing is overwritten")
    assert snapshot(first) == kept, line
    (tmp_path / "file").write_text("mine")
    one_line_error(capfd, main(["export", str(POLICIES / "setting1"), str(tmp_path / "file")]), "is a file")
    assert (tmp_path / "file").read_text() == "mine" and no_leftovers(tmp_path)


def test_export_never_writes_onto_or_into_its_own_source(team, capfd):
    kept = snapshot(team)
    one_line_error(capfd, main(["export", str(team), str(team)]), "is the folder it is made from")
    one_line_error(capfd, main(["export", str(team), str(team / "again")]), "is inside", "made from")
    one_line_error(capfd, main(["export", str(team), str(team / ".." / "team"), "--half"]), "made from")
    assert snapshot(team) == kept and not (team / "again").exists() and no_leftovers(team)


def test_export_to_a_path_that_cannot_be_written_is_one_line(team, tmp_path, capfd):
    one_line_error(capfd, main(["export", str(team), UNWRITABLE]), "dir: cannot write in")
    (tmp_path / "file").write_text("")
    one_line_error(capfd, main(["export", str(team), str(tmp_path / "file" / "out")]), "is a file, not a folder")
    one_line_error(capfd, main(["export", str(team), "s3://bucket/out"]), "storage URI")
    assert not Path("s3:").exists()


def test_export_into_a_new_folder_under_missing_ones_or_an_empty_one(team, tmp_path):
    assert main(["export", str(team), str(tmp_path / "a" / "b" / "c")]) == 0
    (tmp_path / "empty").mkdir()
    assert main(["export", str(team), str(tmp_path / "empty")]) == 0
    assert snapshot(tmp_path / "a" / "b" / "c") == snapshot(tmp_path / "empty")
    assert sorted(snapshot(tmp_path / "empty")) == ["follower.pt", "leader.pt", "policy.json"]
    assert no_leftovers(tmp_path)


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device", "leader.pt"),
                                     KeyboardInterrupt()])
def test_an_export_cut_short_leaves_nothing_behind(team, tmp_path, capfd, monkeypatch, failure):
    import formation.policy

    def half_an_export(policy, out, half=False):
        (Path(out) / "follower.pt").write_bytes(b"half")
        raise failure

    monkeypatch.setattr(formation.policy, "export", half_an_export)
    out = tmp_path / "new" / "deeper" / "export"
    code = main(["export", str(team), str(out)])
    if isinstance(failure, OSError):
        one_line_error(capfd, code, "'leader.pt': No space left on device")
    else:
        assert code == 130 and capfd.readouterr().err.strip() == "formation: interrupted"
    assert not (tmp_path / "new").exists() and no_leftovers(tmp_path)  # nor the folders it made on the way


# ---------------------------------------------------------------------- refit (refused before any refitting)
def test_refit_refuses_existing_unwritable_and_self_referencing_outputs(team, tmp_path, capfd):
    kept = snapshot(team)
    one_line_error(capfd, main(["refit", str(team), str(team)]), "is the folder it is made from")
    one_line_error(capfd, main(["refit", str(team), str(team / "refitted")]), "is inside")
    one_line_error(capfd, main(["refit", str(team), UNWRITABLE]), "dir: cannot write in")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    one_line_error(capfd, main(["refit", str(team), str(tmp_path / "full")]), "not empty")
    assert snapshot(team) == kept and (tmp_path / "full" / "notes.txt").read_text() == "mine"


# ---------------------------------------------------------------------- train (refused before Ray starts)
def test_train_refuses_a_file_a_folder_of_other_things_and_an_unwritable_out(tmp_path, capfd):
    (tmp_path / "file").write_text("mine")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    for out, words in [(tmp_path / "file", ["--out:", "is a file"]), (tmp_path / "full", ["--out:", "not empty"]),
                       (Path(UNWRITABLE), ["--out: cannot write in"]),
                       (tmp_path / "file" / "run", ["is a file, not a folder"])]:
        one_line_error(capfd, main(["train", "configs/smoke.yaml", "--out", str(out)]), *words)
    assert (tmp_path / "file").read_text() == "mine" and sorted(p.name for p in (tmp_path / "full").iterdir()) == [
        "notes.txt"]


# ---------------------------------------------------------------------- evaluate --json
def test_evaluate_checks_its_report_path_before_evaluating(team, tmp_path, capfd, monkeypatch):
    import formation.evaluate

    def never(*args, **kwargs):
        raise AssertionError("evaluated before the report path was checked")

    monkeypatch.setattr(formation.evaluate, "evaluate_policy", never)
    card = (team / "policy.json").read_bytes()
    one_line_error(capfd, main(["evaluate", str(team), "--json", str(team / "policy.json")]), "--json:",
                   "not an evaluation report")
    assert (team / "policy.json").read_bytes() == card
    one_line_error(capfd, main(["evaluate", str(team), "--json", str(tmp_path)]), "--json:", "is a folder")
    one_line_error(capfd, main(["evaluate", str(team), "--json", UNWRITABLE + ".json"]), "--json: cannot write in")
    (tmp_path / "file").write_text("")
    one_line_error(capfd, main(["evaluate", str(team), "--json", str(tmp_path / "file" / "e.json")]), "is a file")


def test_evaluate_replaces_an_earlier_report_whole(team, tmp_path):
    report = tmp_path / "reports" / "team.json"
    args = ["evaluate", str(team), "--episodes", "2", "--workers", "1", "--json", str(report)]
    assert main(args) == 0
    first = report.read_text()
    assert main([*args[:3], "3", *args[4:]]) == 0  # the same command again, as docs/RESULTS.md's are rerun
    assert json.loads(first)["episodes"] == 2 and json.loads(report.read_text())["episodes"] == 3
    assert no_leftovers(tmp_path)


# ---------------------------------------------------------------------- render and show
def test_render_to_a_path_that_cannot_be_written_is_one_line(cli):
    done = cli("render", str(POLICIES / "setting1"), "--out", UNWRITABLE, "--episodes", "1")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == ["formation: error: --out: cannot write in '/proc' (No such file "
                                                "or directory)"]


def test_render_refuses_a_file_and_its_own_source(team, tmp_path, capfd):
    kept = snapshot(team)
    (tmp_path / "file").write_text("mine")
    one_line_error(capfd, main(["render", str(team), "--out", str(tmp_path / "file")]), "--out:", "is a file")
    one_line_error(capfd, main(["render", str(team), "--out", str(team)]), "is the folder it is made from")
    one_line_error(capfd, main(["render", str(team), "--out", str(team / "pictures")]), "is inside")
    assert snapshot(team) == kept and (tmp_path / "file").read_text() == "mine"


def test_render_and_show_draw_into_a_folder_again_replacing_their_own_pictures(team, tmp_path, capsys):
    out = tmp_path / "pictures"
    (tmp_path / "pictures").mkdir()
    (out / "notes.txt").write_text("mine")
    for _ in range(2):  # drawn again, as docs/RESULTS.md's Figures and `make show` do
        assert main(["render", str(team), "--out", str(out), "--episodes", "1"]) == 0
        assert main(["show", "--setting", "1", "--episodes", "1", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["episodes.gif", "notes.txt", "paths.png", "q_values.png",
                                                    "setting1_planner.gif"]
    assert (out / "notes.txt").read_text() == "mine" and no_leftovers(tmp_path)
    printed = capsys.readouterr().out
    assert f"wrote {out / 'episodes.gif'}" in printed and f"wrote {out / 'setting1_planner.gif'}" in printed


def test_show_refuses_a_file_and_an_unwritable_out(tmp_path, capfd):
    (tmp_path / "file").write_text("mine")
    one_line_error(capfd, main(["show", "--episodes", "1", "--out", str(tmp_path / "file")]), "--out:", "is a file")
    one_line_error(capfd, main(["show", "--episodes", "1", "--out", UNWRITABLE]), "--out: cannot write in")
    assert (tmp_path / "file").read_text() == "mine"


# ---------------------------------------------------------------------- argparse's own errors
@pytest.mark.parametrize("args", [["export"], ["evaluate", "x", "--episodes", "many"], ["fly"], [],
                                  ["export", "a", "b", "--veto-fallback", "nowhere"]])
def test_usage_errors_are_one_line_too(args, capfd):
    with pytest.raises(SystemExit) as done:
        main(args)
    assert done.value.code == 2
    out, err = capfd.readouterr()
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("formation") and "error: " in lines[0], err
    assert lines[0].endswith("--help)")
