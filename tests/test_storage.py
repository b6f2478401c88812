"""Run folders on storage URIs (formation.storage), and the resource check before training.

``file://`` URIs take the same pyarrow path as s3:// or gs:// ones, without a cloud."""

import time

import pytest

from formation.config import ConfigError
from formation.recipe.config import RunConfig
from formation.rllib.algorithm import missing_resources
from formation.storage import RemoteRun, is_uri, local_run_folder, staging_folder
from formation.train import check_resources


def make_run(folder, marker: str) -> None:
    (folder / "checkpoint" / "learner").mkdir(parents=True)
    (folder / "checkpoint" / "algorithm_state.pkl").write_text(marker)
    (folder / "checkpoint" / "learner" / "weights").write_text(marker)
    (folder / "config.yaml").write_text("game: {}\n")
    (folder / "metrics.jsonl").write_text('{"env_steps": 1}\n')
    (folder / "tb").mkdir()
    (folder / "tb" / "events").write_text("scalars")  # a folder of files only


def test_push_then_pull_gives_back_the_run_folder(tmp_path):
    uri = f"file://{tmp_path}/bucket/runs/s1"
    remote = RemoteRun(uri)
    assert remote.local == staging_folder(uri) and not remote.has_checkpoint()
    remote.local.mkdir(parents=True, exist_ok=True)
    make_run(remote.local, "first")
    (remote.local / "checkpoint.old").mkdir()  # local leftovers never go up
    remote.push()
    stored = tmp_path / "bucket" / "runs" / "s1"
    assert sorted(p.name for p in stored.iterdir()) == ["checkpoint", "config.yaml", "metrics.jsonl", "tb"]
    assert remote.has_checkpoint()

    make_run_again = remote.local / "checkpoint" / "algorithm_state.pkl"
    make_run_again.write_text("second")
    remote.push()  # the next checkpoint replaces the first, whole
    assert (stored / "checkpoint" / "algorithm_state.pkl").read_text() == "second"
    assert (stored / "checkpoint" / "learner" / "weights").read_text() == "first"

    pulled = local_run_folder(uri)
    assert pulled == remote.local
    assert (pulled / "checkpoint" / "algorithm_state.pkl").read_text() == "second"
    assert (pulled / "metrics.jsonl").read_text() == '{"env_steps": 1}\n'
    assert (pulled / "tb" / "events").read_text() == "scalars"


def test_an_upload_cut_short_leaves_a_whole_checkpoint(tmp_path):
    stored = tmp_path / "runs" / "s1"
    make_run(stored, "old")
    uri = f"file://{stored}"
    # cut while the new checkpoint went up: no marker, so the old one stays
    (stored / "checkpoint.writing").mkdir()
    (stored / "checkpoint.writing" / "algorithm_state.pkl").write_text("half")
    pulled = RemoteRun(uri).pull()
    assert (pulled / "checkpoint" / "algorithm_state.pkl").read_text() == "old"
    assert not (pulled / "checkpoint.writing").exists()
    # cut after the new one was whole and marked, while the old one was being replaced: the new one wins
    (stored / "checkpoint.writing" / "algorithm_state.pkl").write_text("new")
    (stored / "checkpoint.writing.complete").write_text("whole\n")
    (stored / "checkpoint" / "algorithm_state.pkl").unlink()
    pulled = RemoteRun(uri).pull()
    assert (pulled / "checkpoint" / "algorithm_state.pkl").read_text() == "new"
    assert not (pulled / "checkpoint.writing.complete").exists()


def test_bad_uris_get_one_line_naming_the_argument(tmp_path):
    with pytest.raises(ConfigError) as err:
        RemoteRun("nosuchscheme://bucket/run")
    assert str(err.value).startswith("--out: cannot open 'nosuchscheme://bucket/run'") and "s3://" in str(err.value)
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="checkpoint: 'file://.*' does not exist; give the URI of a run folder"):
        local_run_folder(f"file://{tmp_path}/missing")
    assert is_uri("s3://b/r") and not is_uri("runs/s1") and local_run_folder("runs/s1").as_posix() == "runs/s1"


def test_formation_train_refuses_a_uri_that_holds_a_run_unless_resuming(tmp_path):
    from formation.train import train

    stored = tmp_path / "s1"
    make_run(stored, "old")
    with pytest.raises(ConfigError, match="already holds a run; use --resume"):
        train("configs/smoke.yaml", f"file://{stored}")
    with pytest.raises(ConfigError, match="--resume: no checkpoint to resume in 'file://"):
        train(None, f"file://{tmp_path}/empty", resume=True)


def test_missing_resources_name_the_field_and_what_the_cluster_has():
    run = RunConfig.load("configs/smoke.yaml", {"resources.num_rollout_actors": 6,
                                                "resources.cpus_per_rollout_actor": 1.0})
    assert missing_resources(run, {"CPU": 7.0}) is None
    message = missing_resources(run, {"CPU": 4.0})
    assert message.startswith("resources.num_rollout_actors: 6 actors x 1 CPU + the learner need 7 CPUs, "
                              "the Ray cluster has 4")
    two = RunConfig.load("configs/smoke.yaml", {"resources.num_learners": 2, "resources.num_replay_shards": 2})
    assert missing_resources(two, {"CPU": 2.5}).startswith("resources.num_rollout_actors: 2 actors x 0.5 CPU "
                                                           "+ 2 learners need 3 CPUs, the Ray cluster has 2.5")
    gpu = RunConfig.load("configs/smoke.yaml", {"resources.num_gpus_per_learner": 1})
    assert missing_resources(gpu, {"CPU": 8.0}).startswith("resources.num_gpus_per_learner: 1 GPU asked, "
                                                           "the Ray cluster has 0")


def test_a_joined_cluster_gets_time_for_its_nodes_to_arrive(monkeypatch):
    import ray
    import ray.autoscaler.sdk

    run = RunConfig.load("configs/smoke.yaml", {"resources.wait_for_resources_s": 1.5})
    answers = iter([{"CPU": 1.0}, {"CPU": 1.0}, {"CPU": 4.0}])  # a worker node joins on the third look
    monkeypatch.setattr(ray, "cluster_resources", lambda: next(answers))
    asked = []  # the demand the autoscaler is told of, so that it starts the nodes
    monkeypatch.setattr(ray.autoscaler.sdk, "request_resources", lambda bundles: asked.append(bundles))
    check_resources(run, joined=True)
    assert asked == [[{"CPU": 0.5}, {"CPU": 0.5}, {"CPU": 1.0}]]  # smoke: 2 rollout actors of 0.5 CPU, the learner
    monkeypatch.setattr(ray, "cluster_resources", lambda: {"CPU": 1.0})
    started = time.monotonic()
    with pytest.raises(ConfigError, match=r"the Ray cluster has 1; .*\(after waiting 1.5 s\)"):
        check_resources(run, joined=True)
    assert 1.4 <= time.monotonic() - started < 5
    with pytest.raises(ConfigError, match="the Ray cluster has 1; lower num_rollout_actors"):
        check_resources(run, joined=False)  # a local Ray: no waiting, and no autoscaler to ask
    assert len(asked) == 2


def test_a_folder_is_written_whole_or_not_at_all(tmp_path):
    from formation.storage import writing_folder

    out = tmp_path / "made" / "on the way" / "export"
    with pytest.raises(OSError), writing_folder(out) as folder:
        (folder / "half.pt").write_bytes(b"half")
        raise OSError("disk full")
    assert list(tmp_path.iterdir()) == []  # nor the folders made on the way
    with writing_folder(out) as folder:
        (folder / "whole.pt").write_bytes(b"whole")
    assert [p.name for p in out.parent.iterdir()] == ["export"] and (out / "whole.pt").read_bytes() == b"whole"
    with pytest.raises(OSError), writing_folder(out) as folder:  # a folder that filled up meanwhile stays
        (folder / "other.pt").write_bytes(b"other")
    assert [p.name for p in out.iterdir()] == ["whole.pt"] and [p.name for p in out.parent.iterdir()] == ["export"]


def test_files_written_into_a_folder_replace_their_own_names_only(tmp_path):
    from formation.storage import write_text_whole, writing_into

    (tmp_path / "keep.txt").write_text("mine")
    (tmp_path / "episodes.gif").write_text("old")
    with writing_into(tmp_path) as folder:
        (folder / "episodes.gif").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episodes.gif", "keep.txt"]
    assert (tmp_path / "episodes.gif").read_text() == "new" and (tmp_path / "keep.txt").read_text() == "mine"
    with pytest.raises(KeyboardInterrupt), writing_into(tmp_path / "new") as folder:
        (folder / "episodes.gif").write_text("half")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episodes.gif", "keep.txt"]
    write_text_whole(tmp_path / "reports" / "r.json", "{}\n")
    assert sorted(p.name for p in (tmp_path / "reports").iterdir()) == ["r.json"]


def test_outputs_are_checked_in_one_line_before_any_work(tmp_path):
    from formation.storage import check_new_folder, check_outside, check_writable

    (tmp_path / "file").write_text("")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "a").write_text("")
    (tmp_path / "link").symlink_to(tmp_path / "full")
    for call, message in [(lambda: check_writable(tmp_path / "file" / "x", "--out"), "--out: cannot make .* is a file"),
                          (lambda: check_writable("/proc/formation/x", "--out"), "--out: cannot write in '/proc'"),
                          (lambda: check_writable("gs://b/x", "dir"), "dir: 'gs://b/x' is a storage URI"),
                          (lambda: check_new_folder(tmp_path / "full", "dir"), "dir: .* is a folder that is not empty"),
                          (lambda: check_new_folder(tmp_path / "file", "dir"), "dir: .* is a file; allowed"),
                          (lambda: check_outside(tmp_path / "link" / "b", tmp_path / "full", "dir"), "is inside"),
                          (lambda: check_outside(tmp_path / "link", tmp_path / "full", "dir"), "is the folder")]:
        with pytest.raises(ConfigError, match=message) as err:
            call()
        assert "\n" not in str(err.value)
    assert check_new_folder(tmp_path / "new" / "one", "dir", source=tmp_path / "full") == tmp_path / "new" / "one"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "full", "link"]  # the checks leave nothing
