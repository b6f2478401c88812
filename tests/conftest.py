"""Shared helpers for the game tests: a plain-Python reading of the rules in ``docs/GAME.md``.

The reference below is written from that page alone, one entity at a time, so that it can be
checked against ``BatchedGame`` (the only implementation of the rules) step for step.
"""

from __future__ import annotations

import fcntl
import math
import os
import signal
import subprocess
import sys
from dataclasses import dataclass

import pytest

# One torch thread per process: the suite runs two xdist workers and the Ray actors of their runs on two cores,
# and torch's default of a thread per core oversubscribes them (a refit test took 58 s with it, 11 s with one,
# beside a training run). Set before torch loads; Ray's workers and the CLI subprocesses inherit it.
os.environ.setdefault("OMP_NUM_THREADS", "1")

# Action indices (docs/GAME.md, 'Actions').
F, FL, FR, S = 0, 1, 2, 3
SPEC_MOVES = {F: (-1, 0), FL: (-1, -1), FR: (-1, 1), S: (0, 0)}


@dataclass
class RefOutcome:
    positions: list[tuple[int, int]]  # leader first
    obstacles: list[tuple[int, int, int]]  # (row, col, velocity) after the step
    collided: list[bool]
    formation_kept: bool
    reached: bool
    rewards: list[float]
    terminated: bool
    truncated: bool
    success: bool


def reference_step(config, positions, obstacles, actions, steps_before: int) -> RefOutcome:
    """One step of the rules (docs/GAME.md, 'One step'), written out literally."""
    H, W = config.height, config.width
    # 1. Both agents move at once, clamped.
    new = []
    for (r, c), a in zip(positions, actions):
        dr, dc = SPEC_MOVES[int(a)]
        new.append((min(max(r + dr, 0), H - 1), min(max(c + dc, 0), W - 1)))
    # 2. Obstacles: |v| unit sub-steps, reversing before a sub-step that would leave the board.
    reached_cells = []
    moved = []
    for r, c, v in obstacles:
        direction = 1 if v > 0 else -1
        for _ in range(abs(v)):
            if not 0 <= c + direction <= W - 1:
                direction = -direction
            c += direction
            reached_cells.append((r, c))
        moved.append((r, c, direction * abs(v)))
    # 3. Collision: within distance <= 1 of any cell reached after a sub-step.
    collided = [any(math.dist(p, q) <= 1 for q in reached_cells) for p in new]
    # 4. Formation.
    leader, followers = new[0], new[1:]
    kept = all(config.d_min < math.dist(leader, f) < config.d_max for f in followers)
    kept = kept and all(math.dist(followers[i], followers[j]) > config.d_min
                        for i in range(len(followers)) for j in range(i + 1, len(followers)))
    # 5. Reach.
    reached = leader == (0, W // 2)
    formation_term = config.reward_formation_kept if kept else config.reward_formation_broken
    rewards = []
    for i in range(len(new)):
        r = formation_term + (config.reward_collision if collided[i] else 0.0)
        if i == 0 and reached:
            r += config.reward_reach
        rewards.append(r)
    terminated = reached or any(collided) or not kept
    truncated = (steps_before + 1 >= config.max_steps) and not terminated
    success = reached and not any(collided) and kept
    return RefOutcome(new, moved, collided, kept, reached, rewards, terminated, truncated, success)


@pytest.fixture(scope="session")
def reference():
    """The rules in plain Python (see ``reference_step``)."""
    return reference_step


# -- one smoke training (configs/smoke.yaml, under a minute) for every test that needs a trained run

SMOKE_ENV = dict(os.environ, RAY_ADDRESS="")  # a local Ray of its own, not a cluster the shell may know


def run_cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``formation ARGS`` in a subprocess of its own session. Past ``timeout`` the whole session is killed: the
    local Ray a run starts holds the output pipes open, and killing the driver alone would wait on them for ever."""
    cmd = [sys.executable, "-m", "formation.cli", *args]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=SMOKE_ENV,
                          start_new_session=True) as proc:
        try:
            stdout, stderr = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            pytest.fail(f"formation {' '.join(args)} ran past {timeout} s")
        except BaseException:  # pytest-timeout's, or Ctrl-C: leave no run behind
            os.killpg(proc.pid, signal.SIGKILL)
            raise
    return subprocess.CompletedProcess(cmd, proc.returncode, stdout, stderr)


@pytest.fixture(scope="session")
def cli():
    return run_cli


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory, worker_id):
    """A run folder of ``formation train configs/smoke.yaml``; tests only read it (copy it to change it).
    Under pytest-xdist the workers share one: the first to ask trains it, the others wait for it."""
    root = tmp_path_factory.mktemp("smoke") if worker_id == "master" else tmp_path_factory.getbasetemp().parent
    out = root / "smoke-run"
    with open(root / "smoke-run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (out / "result.json").is_file():
            done = run_cli("train", "configs/smoke.yaml", "--out", str(out))
            assert done.returncode == 0, done.stderr[-3000:]
            (root / "smoke-run.stdout").write_text(done.stdout)  # what the user saw (tests/test_cli.py)
    return out


@pytest.fixture(scope="session")
def cluster():
    """A small local Ray (3 logical CPUs, no dashboard: room for two learners) for every test of this session
    (of this xdist worker) that trains in-process; shut down at the end. Starting one costs seconds: start it once."""
    ray = pytest.importorskip("ray")
    if not ray.is_initialized():
        ray.init(num_cpus=3, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="session")
def worker_id(request):
    """pytest-xdist's worker name ("gw0", ...), or "master" without xdist (xdist's own fixture, when it runs)."""
    return getattr(request.config, "workerinput", {}).get("workerid", "master")


@pytest.fixture
def collector():
    """Makes the recipe's ``Collector`` of the smoke config with the given overrides, and its team's networks."""
    from formation.recipe.collect import Collector
    from formation.recipe.config import RunConfig
    from formation.recipe.team import network_specs

    def make(overrides: dict):
        run = RunConfig.load("configs/smoke.yaml", overrides)
        torch = pytest.importorskip("torch")
        torch.manual_seed(0)
        return Collector(run), {m: spec.build() for m, spec in network_specs(run).items()}

    return make


@pytest.fixture
def rollout_actor():
    """Makes a rollout actor (no Ray cluster needed) of the smoke config with the given overrides."""
    pytest.importorskip("ray")
    from formation.recipe.config import RunConfig
    from formation.rllib.algorithm import build_algorithm_config
    from formation.rllib.rollout_actor import RolloutActor

    def make(overrides: dict) -> RolloutActor:
        return RolloutActor(config=build_algorithm_config(RunConfig.load("configs/smoke.yaml", overrides)))

    return make
