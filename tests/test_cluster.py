"""A real Ray cluster on loopback: `ray start --head` (with Ray 2.60's token authentication),
`ray job submit` of the smoke config from the repo, checkpoints to a storage URI, then
`formation evaluate` of that URI, as cluster/README.md walks a user through it.

The head runs with `--block` in a session of its own and its own --temp-dir and ports, so stopping
it (the test's `ray stop`) touches no other Ray on the machine."""

import contextlib
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
# its waits are in Python, which a SIGALRM interrupts: the nodes are stopped, not left to the rest of the suite
pytestmark = pytest.mark.timeout(method="signal")


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


def start_node(temp: Path, env: dict, name: str, *args: str) -> subprocess.Popen:
    """`ray start --block` of one node, in a session of its own (so that killing its group kills the node), with
    its own temp dir and ports (several nodes share this machine's loopback)."""
    node_ports = free_ports(6)
    ports = dict(zip(("--dashboard-agent-listen-port", "--dashboard-agent-grpc-port", "--runtime-env-agent-port",
                      "--metrics-export-port", "--node-manager-port", "--object-manager-port"), node_ports))
    log = (temp / f"{name}.log").open("w")
    return subprocess.Popen([str(BIN / "ray"), "start", "--block", "--node-ip-address=127.0.0.1",
                             *(f"{k}={v}" for k, v in ports.items()), f"--temp-dir={temp / name}", *args],
                            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop_nodes(procs: list[subprocess.Popen], temp: Path) -> None:
    """`ray stop` for these nodes only; fails on processes of theirs that outlive them."""
    for proc in procs:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=60)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    leftover = subprocess.run(["pgrep", "-f", str(temp)], capture_output=True, text=True).stdout.split()
    for pid in leftover:
        os.kill(int(pid), signal.SIGKILL)
    shutil.rmtree(temp, ignore_errors=True)
    assert not leftover, f"processes of the test's Ray nodes outlived them: {leftover}"


def start_cluster(head_cpus: int, worker_cpus: list[int]):
    """A Ray cluster of a head (with the job server, token authentication on) and worker nodes; returns
    (address, env, temp, [head, *workers])."""
    temp = Path(tempfile.mkdtemp(prefix="fr-", dir="/tmp"))  # short: Ray's socket paths must fit
    gcs, dashboard, client = free_ports(3)
    # RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S=0: on SIGTERM the head stops its processes at once, instead of first
    # draining its node (for Ray Serve) for up to 30 s, which it did to the end whenever a Ray had run in this
    # process before (34 s of this test's teardown, 3 s without)
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32),
           "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "RAY_USAGE_STATS_ENABLED": "0",
           "RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S": "0"}
    env.pop("RAY_ADDRESS", None)
    procs = [start_node(temp, env, "head", "--head", f"--port={gcs}", "--include-dashboard=true",
                        "--dashboard-host=127.0.0.1", f"--dashboard-port={dashboard}",
                        f"--ray-client-server-port={client}", f"--num-cpus={head_cpus}")]
    address = f"http://127.0.0.1:{dashboard}"
    try:
        deadline = time.monotonic() + 120
        # wait for the dashboard's HTTP server in-process (a `ray job list` a second is a Python start each) ...
        while not answers(address) and procs[0].poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        # ... then for its job API
        while ray_cli("job", "list", "--address", address, env=env).returncode != 0:
            if procs[0].poll() is not None or time.monotonic() > deadline:
                tail = (temp / "head.log").read_text()[-800:]
                pytest.skip(f"Ray could not start a head node on this machine: {tail}")
            time.sleep(1)
        def worker(i: int) -> subprocess.Popen:  # its name as a resource of its own tells which node is which
            return start_node(temp, env, f"worker{i}", f"--address=127.0.0.1:{gcs}", f"--num-cpus={worker_cpus[i]}",
                              f"--resources={json.dumps({f'worker{i}': 1})}")

        procs += [worker(i) for i in range(len(worker_cpus))]  # after the head is up: they join a running GCS
        retried = set()
        while len(alive_nodes(gcs, env)) < 1 + len(worker_cpus):
            for i, proc in enumerate(procs[1:]):
                # on a busy machine a raylet can time out registering ("timed out during startup"): once more
                if proc.poll() is not None and i not in retried:
                    retried.add(i)
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, signal.SIGKILL)  # what its start left behind
                    procs[1 + i] = worker(i)
            if time.monotonic() > deadline + 60:
                pytest.fail(f"the worker nodes did not join: {(temp / 'worker0.log').read_text()[-800:]}")
            time.sleep(1)
    except BaseException:
        stop_nodes(procs, temp)
        raise
    return address, env, temp, procs, gcs


def alive_nodes(gcs: int, env: dict) -> list[dict]:
    """Ray's state API: the cluster's live nodes."""
    done = ray_cli("list", "nodes", "--address", f"127.0.0.1:{gcs}", "--format", "json", "--detail", env=env)
    try:  # while the head starts, the state API may answer with something else than its list
        return [n for n in json.loads(done.stdout) if n["state"] == "ALIVE"] if done.returncode == 0 else []
    except ValueError:
        return []


@pytest.fixture
def head():
    """A one-node Ray cluster with the job server, token authentication on; yields (address, env)."""
    address, env, temp, procs, _ = start_cluster(2, [])
    try:
        yield address, env
    finally:
        stop_nodes(procs, temp)


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


def finished(address: str, env: dict, job: str, timeout: float, gcs: int | None = None) -> tuple[str, str]:
    """The job's end ("succeeded", "failed" or "stopped") and its whole log, by polling `ray job status`
    (`ray job logs --follow` is known to stop following early, ray-project/ray#51601); a job still running at
    ``timeout`` fails the test with what it waits for."""
    deadline = time.monotonic() + timeout
    while True:
        said = ray_cli("job", "status", "--address", address, job, env=env)
        end = re.search(rf"Job '{job}' (succeeded|failed|stopped)", said.stdout + said.stderr)
        if end or time.monotonic() > deadline:
            logs = ray_cli("job", "logs", "--address", address, job, env=env).stdout
            if not end and gcs is not None:  # what it waits for: actors not alive, demands Ray cannot place, and
                # where its driver stands (py-spy, where installed)
                logs += ray_cli("list", "actors", "--address", f"127.0.0.1:{gcs}", "--filter", "state!=DEAD",
                                "--filter", "state!=ALIVE", env=env).stdout
                logs += ray_cli("status", "--address", f"127.0.0.1:{gcs}", "-v", env=env).stdout
                drivers = subprocess.run(["pgrep", "-f", "formation train"], capture_output=True, text=True)
                for pid in drivers.stdout.split() if (BIN / "py-spy").is_file() else []:
                    logs += subprocess.run([str(BIN / "py-spy"), "dump", "--pid", pid], capture_output=True,
                                           text=True).stdout
            assert end, f"job {job} still running after {timeout:.0f} s: {logs[-6000:]}"
            return end.group(1), logs
        time.sleep(3)


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
    end, logs = finished(address, env, job, timeout=400)
    assert end == "succeeded", logs[-3000:]
    assert "greedy success" in logs

    # a job that asks for more than the cluster has fails fast, in one line, instead of waiting
    done = submit(address, env, "formation", "train", "configs/smoke.yaml", "--out", f"{out}-gpu",
                  "--set", "resources.num_gpus_per_learner=1", "--set", "resources.wait_for_resources_s=2")
    assert done.returncode == 0, done.stderr[-2000:]
    asking = re.search(r"raysubmit_\w+", done.stdout + done.stderr).group(0)
    end, logs = finished(address, env, asking, timeout=200)
    assert end == "failed", logs[-3000:]
    assert ("formation: error: resources.num_gpus_per_learner: 1 GPU asked, the Ray cluster has 0; "
            "allowed here: 0 (the learner then runs on CPU) (after waiting 2 s)") in logs
    assert "Traceback" not in logs

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


def metrics_rows(out: Path) -> list[dict]:
    path = out / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []


def test_a_run_on_four_nodes_loses_a_node_goes_on_counts_the_loss_and_resumes(tmp_path):
    """The service as a cluster runs it: a head (the driver and the job server, no CPUs for actors) and 3 worker
    nodes of 2 CPUs; `ray job submit` of the smoke config with 8 rollout actors, 2 replay shards and 2
    learners. Mid-run the worker node with the most rollout actors and no learner is killed (SIGKILL to its
    raylet's process group): Ray restarts its actors on the other nodes, training goes on to the end, and
    metrics.jsonl counts the restarted actors, the restarted replay shards and the sample requests lost. Then a
    second job resumes the run from its checkpoint on the 3 nodes left."""
    address, env, temp, procs, gcs = start_cluster(0, [2, 2, 2])
    try:
        out, steps = tmp_path / "run", 8000  # the run goes on long enough after the loss for Ray to restart its actors
        done = submit(address, env, "formation", "train", "configs/smoke.yaml", "--out", str(out),
                      "--set", "resources.num_rollout_actors=8", "--set", "resources.cpus_per_rollout_actor=0.25",
                      "--set", "resources.num_replay_shards=2", "--set", "resources.num_learners=2",
                      "--set", "train.learning_starts=200", "--set", f"train.total_env_steps={steps}")
        assert done.returncode == 0, done.stderr[-2000:]
        job = re.search(r"raysubmit_\w+", done.stdout + done.stderr).group(0)
        deadline = time.monotonic() + 300
        while not (metrics_rows(out) and metrics_rows(out)[-1]["learner_updates"] > 0
                   and (out / "checkpoint").is_dir()):
            assert time.monotonic() < deadline, ray_cli("job", "logs", "--address", address, job,
                                                        env=env).stdout[-3000:]
            time.sleep(1)

        listed = ray_cli("list", "actors", "--address", f"127.0.0.1:{gcs}", "--format", "json", "--detail",
                         "--filter", "state=ALIVE", "--limit", "1000", env=env)
        name_of = {n["node_id"]: next(k for k in n["resources_total"] if k.startswith("worker"))
                   for n in alive_nodes(gcs, env) if not n["is_head_node"]}
        status = ray_cli("status", "--address", f"127.0.0.1:{gcs}", env=env).stdout
        assert len(name_of) == 3, f"worker nodes alive: {sorted(name_of.values())}; {status[-1500:]}"
        on = {name: {"rollout": 0, "learner": 0, "replay": 0} for name in name_of.values()}
        for actor in json.loads(listed.stdout):
            kind = {"RolloutActor": "rollout", "ReplayActor": "replay"}.get(
                actor["class_name"], "learner" if "_WrappedExecutable" in actor["class_name"] else None)
            if kind and actor["node_id"] in name_of:
                on[name_of[actor["node_id"]]][kind] += 1
        assert sum(n["rollout"] for n in on.values()) == 8 and sum(n["learner"] for n in on.values()) == 2, on
        victim = max((name for name in on if on[name]["learner"] == 0), key=lambda name: on[name]["rollout"])
        assert on[victim]["rollout"] > 0, on
        killed_at = metrics_rows(out)[-1]["env_steps"]
        os.killpg(procs[1 + int(victim[len("worker"):])].pid, signal.SIGKILL)

        end, logs = finished(address, env, job, timeout=400, gcs=gcs)
        assert end == "succeeded", logs[-3000:]
        rows = metrics_rows(out)
        last = rows[-1]
        assert last["env_steps"] >= steps > killed_at  # training went on after the loss
        assert last["faults/rollout_actor_restarts"] >= on[victim]["rollout"], (on, last)
        assert last["faults/replay_restarts"] == on[victim]["replay"], (on, last)
        # at most 2 requests in flight per actor (max_requests_in_flight_per_env_runner)
        assert 0 <= last["faults/samples_lost"] <= 2 * on[victim]["rollout"], last
        saved = json.loads((out / "result.json").read_text())["env_steps"]

        # the run resumes from its checkpoint on the nodes left
        done = submit(address, env, "formation", "train", "--out", str(out), "--resume",
                      "--set", f"train.total_env_steps={steps + 1000}")
        resumed = re.search(r"raysubmit_\w+", done.stdout + done.stderr).group(0)
        end, logs = finished(address, env, resumed, timeout=200, gcs=gcs)
        assert end == "succeeded", logs[-3000:]
        after = metrics_rows(out)[len(rows):]
        assert after and after[0]["env_steps"] >= saved and after[-1]["env_steps"] >= steps + 1000
        assert after[-1]["faults/rollout_actor_restarts"] >= last["faults/rollout_actor_restarts"]  # carried on
    finally:
        stop_nodes(procs, temp)
