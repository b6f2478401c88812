"""A real Ray cluster on loopback: `ray start --head` (with Ray 2.60's token authentication),
`ray job submit` of the smoke config from the repo, checkpoints to a storage URI, then
`formation evaluate` of that URI, as cluster/README.md walks a user through it.

The head runs with `--block` in a session of its own and its own --temp-dir and ports, so stopping
it (the test's `ray stop`) touches no other Ray on the machine."""

import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
STEPS = 700  # the job's env steps


def free_ports(n: int) -> list[int]:
    sockets = [socket.socket() for _ in range(n)]
    for s in sockets:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in sockets]
    for s in sockets:
        s.close()
    return ports


def ray_cli(*args: str, env: dict, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "ray"), *args], env=env, capture_output=True, text=True, timeout=timeout)


def answers(address: str) -> bool:
    """Whether an HTTP server answers at ``address`` (any status: the head asks for its token)."""
    direct = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback: never through a proxy
    try:
        with direct.open(f"{address}/api/version", timeout=5):
            return True
    except urllib.error.HTTPError:
        return True
    except OSError:
        return False


@pytest.fixture
def head():
    """A one-node Ray cluster with the job server, token authentication on; yields (address, env)."""
    temp = Path(tempfile.mkdtemp(prefix="fr-", dir="/tmp"))  # short: Ray's socket paths must fit
    gcs, dashboard, agent, agent_grpc, runtime_env, metrics, client = free_ports(7)
    # RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S=0: on SIGTERM the head stops its processes at once, instead of first
    # draining its node (for Ray Serve) for up to 30 s, which it did to the end whenever a Ray had run in this
    # process before (34 s of this test's teardown, 3 s without)
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
           "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0"}
    env.pop("RAY_ADDRESS", None)
    log = (temp / "head.log").open("w")
    proc = subprocess.Popen(
        [str(BIN / "ray"), "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={gcs}",
         "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard}",
         f"--dashboard-agent-listen-port={agent}", f"--dashboard-agent-grpc-port={agent_grpc}",
         f"--runtime-env-agent-port={runtime_env}", f"--metrics-export-port={metrics}",
         f"--ray-client-server-port={client}", "--num-cpus=2", f"--temp-dir={temp / 'ray'}"],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    address = f"http://127.0.0.1:{dashboard}"
    try:
        deadline = time.monotonic() + 120
        # wait for the dashboard's HTTP server in-process (a `ray job list` a second is a Python start each) ...
        while not answers(address) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        # ... then for its job API
        while ray_cli("job", "list", "--address", address, env=env).returncode != 0:
            if proc.poll() is not None or time.monotonic() > deadline:
                tail = (temp / "head.log").read_text()[-800:]
                pytest.skip(f"Ray could not start a head node on this machine: {tail}")
            time.sleep(1)
        yield address, env
    finally:
        try:  # `ray stop` for this head only
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=60)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        log.close()
        leftover = subprocess.run(["pgrep", "-f", str(temp)], capture_output=True, text=True).stdout.split()
        for pid in leftover:
            os.kill(int(pid), signal.SIGKILL)
        shutil.rmtree(temp, ignore_errors=True)
        assert not leftover, f"processes of the test's Ray head outlived it: {leftover}"


def submit(address: str, env: dict, *entrypoint: str) -> subprocess.CompletedProcess:
    """`ray job submit --no-wait`, retried while the head's job agent is still coming up."""
    deadline = time.monotonic() + 90
    while True:
        done = ray_cli("job", "submit", "--address", address, "--working-dir", str(REPO), "--no-wait", "--",
                       *entrypoint, env=env)
        if done.returncode == 0 or "No available agent" not in done.stderr + done.stdout \
                or time.monotonic() > deadline:
            return done
        time.sleep(2)


def test_ray_job_submit_trains_on_a_cluster_and_the_checkpoint_evaluates(head, tmp_path):
    address, env = head
    out = f"file://{tmp_path}/storage/smoke"

    no_token = {k: v for k, v in env.items() if k != "RAY_AUTH_TOKEN"}
    no_token["RAY_AUTH_TOKEN_PATH"] = str(tmp_path / "no-such-token")
    refused = ray_cli("job", "list", "--address", address, env=no_token)
    assert refused.returncode != 0  # the cluster really asks for the token

    # the job is the point, not learning: one rollout actor, a few learner updates (smoke: 500 records before the first)
    done = submit(address, env, "formation", "train", "configs/smoke.yaml", "--out", out,
                  "--set", f"train.total_env_steps={STEPS}", "--set", "resources.num_rollout_actors=1")
    assert done.returncode == 0, done.stderr[-2000:]
    job = re.search(r"raysubmit_\w+", done.stdout + done.stderr).group(0)
    logs = ray_cli("job", "logs", "--address", address, "--follow", job, env=env, timeout=400)
    status = ray_cli("job", "status", "--address", address, job, env=env)
    assert f"Job '{job}' succeeded" in status.stdout + status.stderr, logs.stdout[-3000:]
    assert "greedy success" in logs.stdout

    # a job that asks for more than the cluster has fails fast, in one line, instead of waiting
    done = submit(address, env, "formation", "train", "configs/smoke.yaml", "--out", f"{out}-gpu",
                  "--set", "resources.num_gpus_per_learner=1", "--set", "resources.wait_for_resources_s=2")
    assert done.returncode == 0, done.stderr[-2000:]
    asking = re.search(r"raysubmit_\w+", done.stdout + done.stderr).group(0)
    logs = ray_cli("job", "logs", "--address", address, "--follow", asking, env=env, timeout=200)
    status = ray_cli("job", "status", "--address", address, asking, env=env)
    assert f"Job '{asking}' failed" in status.stdout + status.stderr
    assert ("formation: error: resources.num_gpus_per_learner: 1 GPU asked, the Ray cluster has 0; "
            "allowed here: 0 (the learner then runs on CPU) (after waiting 2 s)") in logs.stdout
    assert "Traceback" not in logs.stdout

    stored = tmp_path / "storage" / "smoke"
    assert (stored / "checkpoint" / "algorithm_state.pkl").is_file()
    assert not (stored / "checkpoint.writing").exists()
    assert json.loads((stored / "result.json").read_text())["env_steps"] >= STEPS

    # `formation evaluate` of the URI, off the cluster: its entry point in this process (a Python start fewer;
    # one planner worker starts no Ray)
    from formation.cli import main

    assert main(["evaluate", out, "--episodes", "20", "--workers", "1", "--json", str(tmp_path / "eval.json")]) == 0
    report = json.loads((tmp_path / "eval.json").read_text())
    assert report["episodes"] == 20 and report["env_steps"] >= STEPS
