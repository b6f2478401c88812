"""Failures during `formation train` (docs/FAULTS.md): a rollout actor, the replay actor or the
learner whose process dies mid-run, a driver killed outright, and SIGTERM.

The actors are killed as a crash kills them: SIGKILL to their process, found by actor id."""

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable

import pytest

ray = pytest.importorskip("ray")

from formation.config import RunFailed  # noqa: E402
from formation.train import recover_checkpoint, train  # noqa: E402

SMOKE = "configs/smoke.yaml"


def rollout_actors(algo) -> dict[int, tuple[int, str]]:
    """worker index -> (process id, actor id) of every rollout actor."""
    found = algo.env_runner_group.foreach_env_runner(
        lambda runner: (runner.worker_index, os.getpid(), ray.get_runtime_context().get_actor_id()),
        local_env_runner=False)
    return {index: (pid, actor_id) for index, pid, actor_id in found}


def replay_process(algo) -> tuple[int, str]:
    return ray.get(algo.replays[0].__ray_call__.remote(
        lambda replay: (os.getpid(), ray.get_runtime_context().get_actor_id())))


def last_row(out) -> dict:
    return json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])


def test_killed_rollout_and_replay_actors_are_restarted_the_replay_refilled_and_the_run_finishes(cluster, tmp_path):
    """One run, two crashes: a rollout actor at 400 env steps, then the replay actor once learning is under way.
    Learning starts at 200 records (smoke: 500), so that the refill and the learning after it fit in 2200 env steps."""
    out = tmp_path / "run"
    seen: dict = {}
    learning_starts = 200

    def kill_an_actor_then_the_replay(algo, row):
        if "actor_killed" not in seen and row["env_steps"] >= 400:
            index, (pid, actor_id) = sorted(rollout_actors(algo).items())[0]
            seen["actor_killed"] = (index, pid, actor_id)
            os.kill(pid, signal.SIGKILL)
        elif "actor_killed" in seen and "replay_killed" not in seen and row["learner_updates"] > 0 \
                and row["env_steps"] >= 1000:
            seen["replay_killed"] = replay_process(algo)
            seen["updates_at_kill"] = algo.counters["updates"]
            os.kill(seen["replay_killed"][0], signal.SIGKILL)
        seen["actors"] = rollout_actors(algo)  # the last iteration's actors
        seen["healthy"] = algo.env_runner_group.healthy_worker_ids()
        seen["replay"] = algo.replay_stats()[0]
        seen["process"] = replay_process(algo)

    summary = train(SMOKE, str(out), overrides={"train.total_env_steps": 2200, "train.prioritized": True,
                                                "train.learning_starts": learning_starts},
                    quiet=True, on_iteration=kill_an_actor_then_the_replay)
    row = last_row(out)
    assert row["env_steps"] >= 2200 and summary["episodes"] == 50
    # the rollout actor: Ray restarted the same actor in a new process, and both actors sample again
    index, pid, actor_id = seen["actor_killed"]
    assert row["faults/rollout_actor_restarts"] >= 1
    assert sorted(seen["healthy"]) == [1, 2]
    new_pid, new_actor_id = seen["actors"][index]
    assert new_actor_id == actor_id and new_pid != pid
    # the replay: restarted; learning paused while it refilled (what the ratio owed then was skipped) ...
    assert row["faults/replay_restarts"] == 1
    assert row["faults/updates_skipped"] > 0
    # ... and went on after it
    assert row["learner_updates"] > seen["updates_at_kill"] + 20
    assert seen["process"][1] == seen["replay_killed"][1] and seen["process"][0] != seen["replay_killed"][0]
    assert seen["replay"]["replay_env_steps"] < row["env_steps"]  # the new replay holds only what came after
    assert seen["replay"]["replay_records"] >= learning_starts  # refilled to learning_starts at least


def test_a_killed_learner_stops_the_run_in_one_line_and_keeps_the_last_checkpoint(cluster, tmp_path):
    out = tmp_path / "run"
    seen: dict = {}

    def kill_the_learner(algo, row):
        saved = out / "checkpoint" / "algorithm_state.pkl"
        if "killed" not in seen and saved.is_file() and row["learner_updates"] > 0:
            seen["saved"] = saved.stat().st_mtime_ns
            pid, = [r.get() for r in algo.learner_group.foreach_learner(lambda learner: os.getpid())]
            seen["killed"] = pid
            os.kill(pid, signal.SIGKILL)

    with pytest.raises(RunFailed) as err:
        # the learner is the point: one rollout actor, and learning from 64 records on
        train(SMOKE, str(out), overrides={"train.total_env_steps": 100_000, "resources.num_rollout_actors": 1,
                                          "train.learning_starts": 64}, quiet=True, on_iteration=kill_the_learner)
    message = str(err.value)
    assert message.startswith("the learner died (") and "\n" not in message
    assert message.endswith(f"the last checkpoint, {out / 'checkpoint'}, is kept: continue with --resume")
    assert (out / "checkpoint" / "algorithm_state.pkl").stat().st_mtime_ns == seen["saved"]


def rows_of(out) -> list[dict]:
    """The metrics rows written whole so far (a running driver may be midway through the last line)."""
    text = (out / "metrics.jsonl").read_text()
    return [json.loads(line) for line in text[: text.rfind("\n") + 1].splitlines()]


def saved_env_steps(out) -> int:
    """The env steps of the last checkpoint (training.json is written whole with each), 0 before the first."""
    record = out / "training.json"
    return json.loads(record.read_text())["env_steps"] if record.is_file() else 0


def wait_for(proc: subprocess.Popen, ready: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 240
    while not ready():
        assert proc.poll() is None and time.monotonic() < deadline, what
        time.sleep(0.5)


def test_a_killed_driver_leaves_a_checkpoint_that_resume_continues_and_sigterm_saves_one(tmp_path):
    """A driver killed outright (SIGKILL to it and the local Ray it started: no chance to save) leaves its last
    periodic checkpoint; `--resume` goes on from its counters; SIGTERM then stops the resumed run as Ctrl-C does:
    a checkpoint saved, exit status 130."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "formation.cli", "train", SMOKE, "--out", str(out),
           "--set", "train.total_env_steps=1000000", "--set", "checkpoint.every_iterations=1",
           "--set", "resources.num_rollout_actors=1"]  # the driver is the point: one process fewer to start, twice
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        # killed once a checkpoint holds env steps (not after a fixed sleep): the driver is training by then
        wait_for(proc, lambda: (out / "checkpoint" / "algorithm_state.pkl").is_file() and saved_env_steps(out) > 0,
                 "training did not start")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    steps_logged = len(rows_of(out))
    assert steps_logged > 0
    saved_steps = json.loads((out / "training.json").read_text())["env_steps"]  # written with each checkpoint
    assert saved_steps > 0

    resumed = subprocess.Popen([sys.executable, "-m", "formation.cli", "train", "--out", str(out), "--resume"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        # a row of the resumed run's own: the killed driver may have logged one past its last checkpoint
        wait_for(resumed, lambda: any(r["env_steps"] > saved_steps for r in rows_of(out)[steps_logged:]),
                 "the resumed run did not train")
        signalled = time.time()
        resumed.send_signal(signal.SIGTERM)
        _, err = resumed.communicate(timeout=120)
    finally:
        if resumed.poll() is None:
            os.killpg(resumed.pid, signal.SIGKILL)
            resumed.wait(timeout=60)
    # the resumed run started from the checkpoint's counters, not from zero (an iteration on a loaded machine may
    # sample nothing, and its row repeats them: seen once with the full suite beside other work)
    resumed_rows = rows_of(out)[steps_logged:]
    assert resumed_rows and all(r["env_steps"] >= saved_steps for r in resumed_rows)
    assert resumed.returncode == 130
    assert "stopped: checkpoint saved" in err and "Traceback" not in err
    assert (out / "checkpoint" / "algorithm_state.pkl").stat().st_mtime >= signalled - 1
    assert json.loads((out / "training.json").read_text())["env_steps"] > saved_steps


def test_a_save_cut_between_its_renames_is_recovered(tmp_path):
    """save_checkpoint renames checkpoint -> checkpoint.old, then checkpoint.writing -> checkpoint:
    a crash between the two leaves the old one, which the next start puts back."""
    (tmp_path / "checkpoint.old").mkdir()
    (tmp_path / "checkpoint.old" / "algorithm_state.pkl").write_text("old")
    (tmp_path / "checkpoint.writing").mkdir()  # maybe half written: never used
    recover_checkpoint(tmp_path)
    assert (tmp_path / "checkpoint" / "algorithm_state.pkl").read_text() == "old"
    recover_checkpoint(tmp_path)  # nothing to do the second time
    assert (tmp_path / "checkpoint").is_dir()
