"""``formation train``: run FormationDQN from a config until its env-step budget, with progress,
metrics (JSON lines and TensorBoard), checkpoints, and resume.

Run folder (``--out``): ``config.yaml`` (the resolved config), ``metrics.jsonl`` (one line per
iteration), ``tb/`` (TensorBoard), ``checkpoint/`` (RLlib's own format, the latest), ``result.json``
(the final greedy evaluation, its seed and env steps) and ``training.json`` (how the checkpoint was
trained: env steps, learner updates, wall time summed over ``--resume`` sessions, hardware, the code's
commit, each session's start and end; written with every checkpoint, so it describes that checkpoint).
A policy card (``formation.policy``) carries both. ``--out`` may also be a storage URI (``formation.storage``).

What a failure costs: docs/FAULTS.md.
"""

from __future__ import annotations

import json
import math
import os
import platform
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from formation.config import ConfigError, RunFailed
from formation.pictures import write_episodes_gif
from formation.policy import TRAINING  # the run folder's training record (``training_record``)
from formation.recipe.config import RunConfig
from formation.storage import RemoteRun, is_uri, write_text_whole

CHECKPOINT = "checkpoint"
REFIT_ROUNDS = "refit.rounds"  # the refit phase's finished rounds, until its team is in refitted/
# what --set may change when resuming: how long to train, a fine-tuning phase (a lower lr, and a
# replay refilled to learning_starts records before the first update, as it starts empty), and where it
# runs (a run started on a cluster or a GPU machine goes on on a laptop, and the other way round), and the
# refit that follows training (formation refit)
RESUMABLE = {"train.total_env_steps", "train.lr", "train.learning_starts"}
RESUMABLE_SECTIONS = ("resources", "refit")
FAULT_COUNTERS = ("rollout_actor_restarts", "replay_restarts", "updates_skipped", "samples_lost")
# each module's learner results in metrics.jsonl, as learner/<module>/<name>
LEARNER_METRICS = {"q_mean": "q_mean", "td_abs_mean": "td_abs_mean", "total_loss": "total_loss",
                   "default_optimizer_learning_rate": "lr", "safety_loss": "safety_loss",
                   "safety_error": "safety_error"}


class Stop(KeyboardInterrupt):
    """Raised by the SIGTERM handler so that training stops like on Ctrl-C (and the CLI exits 130)."""


def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "/"))
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def start_ray(run: RunConfig) -> None:
    import ray

    if ray.is_initialized():
        return
    if os.environ.get("RAY_ADDRESS"):  # inside `ray job submit`: join the cluster
        ray.init()
    else:  # a laptop: a local Ray sized to the machine, no dashboard
        ray.init(num_cpus=os.cpu_count() or 2, include_dashboard=False, log_to_driver=False)


def check_resources(run: RunConfig, joined: bool = False) -> None:
    """Fail fast, in one line, when the run asks for more than the Ray cluster has (Ray would wait
    for ever). On a cluster the run joined, nodes may still be joining: tell its autoscaler what the run
    needs (``ray.autoscaler.sdk.request_resources``, so that it starts nodes before any actor waits) and
    wait up to ``resources.wait_for_resources_s`` for them."""
    import ray

    from formation.rllib.algorithm import missing_resources, resource_bundles

    missing = missing_resources(run, ray.cluster_resources())
    if missing is not None and joined:
        from ray.autoscaler.sdk import request_resources

        request_resources(bundles=resource_bundles(run))
    deadline = time.monotonic() + (run.resources.wait_for_resources_s if joined else 0.0)
    while missing is not None:
        if time.monotonic() >= deadline:
            waited = f" (after waiting {run.resources.wait_for_resources_s:g} s)" if joined else ""
            raise ConfigError(missing + waited)
        time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
        missing = missing_resources(run, ray.cluster_resources())


def checkpoint_path(out: Path) -> Path:
    return out / CHECKPOINT


def recover_checkpoint(out: Path) -> None:
    """After a crash between the two renames of ``save_checkpoint``, the previous checkpoint is
    ``checkpoint.old``: put it back. A half-written ``checkpoint.writing`` is never used."""
    final, old = checkpoint_path(out), out / f"{CHECKPOINT}.old"
    if not final.exists() and old.is_dir():
        old.rename(final)


def save_checkpoint(algo, out: Path) -> Path:
    """Write the checkpoint next to the old one, then swap, so a crash never leaves none."""
    final = checkpoint_path(out)
    fresh = out / f"{CHECKPOINT}.writing"
    shutil.rmtree(fresh, ignore_errors=True)
    algo.save_to_path(str(fresh.resolve()))
    old = out / f"{CHECKPOINT}.old"
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        final.rename(old)
    fresh.rename(final)
    shutil.rmtree(old, ignore_errors=True)
    return final


class Progress:
    """One status line, rewritten in place on a terminal and printed every ``every`` s otherwise."""

    def __init__(self, total: int, every: float = 30.0):
        self.total, self.every, self.last = total, every, 0.0
        self.tty = sys.stdout.isatty()

    def show(self, env_steps: int, greedy: float | None, steps_per_s: float, final: bool = False) -> None:
        now = time.monotonic()
        if not (self.tty or final or now - self.last >= self.every):
            return
        self.last = now
        frac = min(1.0, env_steps / self.total)
        bar = "#" * int(frac * 30)
        greedy_text = f"{greedy:6.1%}" if greedy is not None else "   n/a"
        line = (f"[{bar:30s}] {env_steps:>9,}/{self.total:,} env steps  greedy success {greedy_text}  "
                f"{steps_per_s:7,.0f} steps/s")
        print(("\r" if self.tty else "") + line, end="\n" if (final or not self.tty) else "", flush=True)


def train(config_path: str | None, out: str | None, resume: bool = False, overrides: dict | None = None,
          quiet: bool = False, on_iteration: Callable[[Any, dict], None] | None = None) -> dict:
    """Train; returns the final greedy evaluation summary. Bad input raises ConfigError before Ray starts.

    ``out`` is a local folder or a storage URI (``formation.storage``). ``on_iteration(algo, row)``
    is called after every iteration with the metrics row just written (for tools that watch a run)."""
    remote = None
    if out is not None and is_uri(out):  # train in a local staging folder, copy it up as it goes
        remote = RemoteRun(str(out))
        if resume and not remote.has_checkpoint():
            raise ConfigError(f"--resume: no checkpoint to resume in {out!r} (expected {out.rstrip('/')}/"
                              f"{CHECKPOINT}); train without --resume first")
        out_dir = remote.pull() if resume else remote.local
        if not resume:
            if remote.has_checkpoint():
                raise ConfigError(f"--out: {out!r} already holds a run; use --resume to continue it "
                                  "or choose another --out")
            remote.check_writable()
            shutil.rmtree(out_dir, ignore_errors=True)
    else:
        out_dir = Path(out) if out else Path("runs") / (Path(config_path).stem if config_path else "run")
    recover_checkpoint(out_dir)
    kept_in = out if remote is not None else checkpoint_path(out_dir)  # where users find the checkpoint
    if resume:
        saved = out_dir / "config.yaml"
        if not checkpoint_path(out_dir).is_dir() or not saved.is_file():
            raise ConfigError(f"--resume: no checkpoint to resume in {str(out_dir)!r} "
                              f"(expected {str(checkpoint_path(out_dir))!r}); train without --resume first")
        run = resumed_config(saved, overrides)
    else:
        if config_path is None:
            raise ConfigError("config: give a config file, e.g. configs/quickstart.yaml")
        run = RunConfig.load(config_path, overrides)
        if checkpoint_path(out_dir).exists():
            raise ConfigError(f"--out: {str(out_dir)!r} already holds a run; use --resume to continue it "
                              "or choose another --out")
    if run.games is not None:
        raise ConfigError("games: a team of many games trains in one process for now; allowed: formation train "
                          "CONFIG --no-ray")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.yaml").write_text(yaml.safe_dump(run.to_dict(), sort_keys=False))
    earlier = read_training_record(out_dir) if resume else None
    session = {"started": now(), "commit": code_commit()}
    session_clock = time.monotonic()  # the session's wall time counts Ray's start and the restore too

    earlier_seconds = sum(s["seconds"] for s in (earlier or {}).get("sessions", []))

    def wall_seconds() -> float:  # the run's training time so far, earlier sessions included
        return round(earlier_seconds + time.monotonic() - session_clock, 3)

    previous_handler = signal.signal(signal.SIGTERM, _raise_stop)
    try:
        algo = _start(run, out_dir, resume)
        # Ray installs its own SIGTERM handler while starting; ours goes back on top.
        signal.signal(signal.SIGTERM, _raise_stop)
    except BaseException as err:
        signal.signal(signal.SIGTERM, previous_handler)
        if isinstance(err, KeyboardInterrupt):  # Ctrl-C, or SIGTERM (Stop)
            print("\nstopped before training began; nothing to save", file=sys.stderr)
        raise

    from tensorboardX import SummaryWriter

    from formation.rllib.algorithm import modules_of, play_team

    writer = SummaryWriter(str(out_dir / "tb"))
    metrics_file = (out_dir / "metrics.jsonl").open("a")
    session.update(hardware=hardware(), env_steps=[algo.counters["env_steps"]] * 2)

    def save(algo) -> None:
        save_checkpoint(algo, out_dir)
        session.update(ended=now(), seconds=round(time.monotonic() - session_clock, 3),
                       env_steps=[session["env_steps"][0], algo.counters["env_steps"]])
        record = training_record(earlier, session, algo.counters)
        write_text_whole(out_dir / TRAINING, json.dumps(record, indent=2) + "\n")  # whole, like the checkpoint
        if remote is not None:
            metrics_file.flush()
            writer.flush()
            remote.push()

    progress = Progress(run.train.total_env_steps)
    iteration, kept_at = 0, None
    started, at_start = time.perf_counter(), dict(algo.counters)
    try:
        while algo.counters["env_steps"] < run.train.total_env_steps:
            result = algo.train()
            iteration += 1
            row = _metrics_row(algo, result, started, at_start)
            metrics_file.write(json.dumps(row) + "\n")
            metrics_file.flush()
            for key, value in row.items():
                if math.isfinite(value):  # e.g. no episode ended this iteration: nothing to plot
                    writer.add_scalar(key, value, int(row["env_steps"]))
            if not quiet:
                progress.show(int(row["env_steps"]), algo.last_eval.get("success"), row["env_steps_per_s"])
            if algo.last_eval_weights is not None and algo.last_eval["env_steps"] != kept_at:
                kept_at = algo.last_eval["env_steps"]
                keep_best(run, modules_of(run, algo.last_eval_weights), algo.last_eval, out_dir, session,
                          wall_seconds())
            if iteration % run.checkpoint.every_iterations == 0:
                save(algo)
            if on_iteration is not None:
                on_iteration(algo, row)
        modules = algo.local_modules()  # the final team: evaluated, and perhaps the best
        final = play_team(run, modules, run.eval.episodes, run.eval.seed, record=run.eval.gif_episodes)
        summary = algo.last_eval = final["summary"]
        keep_best(run, modules, {**summary, "env_steps": algo.counters["env_steps"]}, out_dir, session,
                  wall_seconds())
        gif = write_episodes_gif(out_dir / "greedy.gif", final["screens"]) if final["screens"] else None
        (out_dir / "result.json").write_text(json.dumps({"env_steps": algo.counters["env_steps"],
                                                         "seed": run.eval.seed, "greedy": summary}, indent=2))
        save(algo)
    except RunFailed as err:  # nothing left to save: the last checkpoint stays as it was
        raise RunFailed(f"{err}; the last checkpoint, {kept_in}, is kept: continue with --resume") from None
    except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (Stop)
        save(algo)
        print(f"\nstopped: checkpoint saved in {kept_in}; continue with --resume", file=sys.stderr)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous_handler)
        metrics_file.close()
        writer.close()
        algo.stop()
    if not quiet:
        rate = (algo.counters["env_steps"] - at_start["env_steps"]) / max(time.perf_counter() - started, 1e-9)
        progress.show(algo.counters["env_steps"], summary["success"], rate, final=True)
    if run.refit.rounds:  # after Ray has stopped, so that the refit's planner workers have the cores
        summary = refit_phase(out_dir, run, say=(lambda line: None) if quiet else
                              (lambda line: print(line, flush=True)))
        if remote is not None:
            remote.push()
    if not quiet:
        print(f"greedy success {summary['success']:.1%} on {summary['episodes']} held-out scenarios; "
              f"run folder {out if remote is not None else out_dir}")
        if gif is not None:
            print(f"greedy episodes: {f'{out}/{gif.name}' if remote is not None else gif}")
    return summary


def keep_best(run: RunConfig, modules: dict, evaluation: dict, out_dir: Path, session: dict,
              wall_seconds: float) -> bool:
    """The team of ``modules`` and its training ``evaluation`` into the run's ``best/`` where it is the best so
    far (``formation.policy.keep_if_best``); its card records that evaluation, the config, this session's code and
    the run's ``wall_seconds`` of training up to it."""
    from formation.policy import keep_if_best
    from formation.rllib.algorithm import team_of

    team = team_of(run, modules, source=str(out_dir), env_steps=evaluation["env_steps"])
    team.training = {"config": run.to_dict(), "env_steps": evaluation["env_steps"], "commit": session["commit"],
                     "hardware": session.get("hardware"), "wall_seconds": wall_seconds,
                     "evaluation": {"env_steps": evaluation["env_steps"], "seed": run.eval.seed,
                                    "greedy": {k: v for k, v in evaluation.items() if k != "env_steps"}}}
    return keep_if_best(team, out_dir)


# ---------------------------------------------------------------------- the refit phase
def refit_phase(out_dir: Path, run: RunConfig, say: Callable[[str], None]) -> dict:
    """The run's last phase (``refit:`` with ``rounds`` > 0): the trained team's safety heads refitted
    (``formation.recipe.safety_refit``), evaluated greedily as training's evaluations are, and kept in
    ``refitted/`` as an export whose card records the training, the refit and that evaluation. A refitted team
    already there is replaced only once the new one is whole. Returns the evaluation's summary."""
    from formation.evaluate import play_greedy
    from formation.policy import REFITTED, load, replace_export

    policy = load(checkpoint_path(out_dir))
    say(f"refit: {run.refit.rounds} round(s) of {run.refit.episodes:,} games, labels over {run.refit.horizon} steps")
    # a run stopped in its refit phase goes on, with --resume, after the last round it finished
    report = refit_recorded(policy, run.refit, say, keep=out_dir / REFIT_ROUNDS)
    clock = time.monotonic()
    summary = play_greedy(policy.game, policy.act_batch, run.eval.episodes, run.eval.seed)["summary"]
    report.update(evaluation={"seed": run.eval.seed, "greedy": summary})
    report["seconds"] += time.monotonic() - clock
    final = replace_export(policy, out_dir / REFITTED)
    shutil.rmtree(out_dir / REFIT_ROUNDS, ignore_errors=True)
    say(f"refitted in {report['seconds'] / 60:.1f} min: greedy success {summary['success']:.1%} on "
        f"{summary['episodes']} held-out scenarios; the team: {final}")
    return summary


def refit_recorded(policy, settings, say: Callable[[str], None], keep: Path | None = None) -> dict:
    """``formation.recipe.safety_refit.refit`` of ``policy`` (its finished rounds kept in ``keep``), its report
    (returned) kept on the policy's card with the refit's start, end, commit and hardware, as training's record;
    an earlier refit's report stays inside it (``earlier``)."""
    from formation.recipe.safety_refit import refit

    earlier, started = policy.refit_report, now()
    report = refit(policy, settings, say=say, keep=keep)
    report.update(started=started, ended=now(), commit=code_commit(), hardware=hardware())
    policy.refit_report = {**report, "earlier": earlier} if earlier else report
    return policy.refit_report


def resumed_config(saved: Path, overrides: dict | None) -> RunConfig:
    """The config of the run being resumed (its folder's ``config.yaml``), with the ``--set`` overrides a resume
    may make: those of ``RESUMABLE`` and ``RESUMABLE_SECTIONS``, the rest refused in one line."""
    changed = sorted(k for k in overrides or {} if k not in RESUMABLE and k.split(".")[0] not in RESUMABLE_SECTIONS)
    if changed:
        raise ConfigError(f"--resume: --set {changed[0]} would change the run being resumed; allowed: "
                          f"{', '.join(sorted(RESUMABLE))}, {', '.join(s + '.*' for s in RESUMABLE_SECTIONS)}")
    return RunConfig.load_saved(saved, overrides)


# ---------------------------------------------------------------------- the training record
def training_record(earlier: dict | None, session: dict, counters: dict) -> dict:
    """``training.json``: the ``earlier`` record (None for a new run) with this ``session`` (its start and
    end, seconds, env steps from and to, commit, hardware) added or brought up to date, and the counters
    of the checkpoint just saved. Wall time is the sum of the sessions' seconds: a resumed run adds to it."""
    ordered = {k: session[k] for k in ("started", "ended", "seconds", "env_steps", "commit", "hardware")}
    sessions = [*(earlier or {}).get("sessions", []), ordered]
    return {"env_steps": int(counters["env_steps"]), "learner_updates": int(counters["updates"]),
            "wall_seconds": round(sum(s["seconds"] for s in sessions), 3),
            "started": sessions[0]["started"], "ended": session["ended"],
            "commit": session["commit"], "hardware": session["hardware"], "sessions": sessions}


def read_training_record(out_dir: Path) -> dict | None:
    """The run's ``training.json``; None if it has none (a run trained before there was one) or it is
    unreadable: a resume then records its own sessions only, and never fails for it."""
    try:
        record = json.loads((out_dir / TRAINING).read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(record, dict) and isinstance(record.get("sessions"), list)
            and all(isinstance(s, dict) and isinstance(s.get("seconds"), int | float) for s in record["sessions"])):
        return None
    return record


def now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def code_commit() -> str:
    """The git commit of the code running: ``git rev-parse HEAD`` of the repository the package is tracked
    in, ``<sha>-dirty`` when its tracked files have changes; ``unknown`` when it is in none (an installed
    package) or git is missing. Never raises: no run fails for it."""
    package = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True, timeout=20,
                              check=True).stdout.strip()

    try:
        git("ls-files", "--error-unmatch", "__init__.py")  # tracked: not a copy in site-packages inside some repo
        sha = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{sha}-dirty" if dirty else sha


def hardware() -> dict[str, Any]:
    """What a session ran on: the driver's CPU, the Ray cluster (nodes, CPUs, GPUs and their kind; None
    when Ray is not running, as in ``formation refit``) and the versions. GPUs are named by Ray's
    ``accelerator_type`` resources, else by torch where Ray is not running; the driver claims no GPU."""
    from importlib.metadata import PackageNotFoundError, version

    import torch

    info: dict[str, Any] = {"cpu": _cpu_model(), "cpus": os.cpu_count(), "gpu": None, "gpus": 0,
                            "ray_nodes": None, "ray_cpus": None, "torch": torch.__version__, "ray": None,
                            "python": platform.python_version(), "platform": platform.platform()}
    try:
        info["ray"] = version("ray")
    except PackageNotFoundError:
        pass
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        try:
            resources = ray.cluster_resources()
            info["ray_nodes"] = sum(1 for node in ray.nodes() if node.get("Alive"))
            info["ray_cpus"] = resources.get("CPU", 0.0)
            info["gpus"] = resources.get("GPU", 0.0)
            kinds = sorted(k.partition(":")[2] for k in resources if k.startswith("accelerator_type:"))
            info["gpu"] = ", ".join(kinds) or ("GPU" if info["gpus"] else None)
        except Exception:  # a cluster that cannot be asked: the driver's own entries stay
            pass
    elif torch.cuda.is_available():
        info["gpus"] = torch.cuda.device_count()
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def _start(run: RunConfig, out_dir: Path, resume: bool):
    """Start (or join) Ray and build the algorithm, fresh or from the run's checkpoint."""
    start_ray(run)
    check_resources(run, joined=bool(os.environ.get("RAY_ADDRESS")))
    from formation.rllib.algorithm import build_algorithm_config

    algo = build_algorithm_config(run).build_algo()
    if resume:  # built from today's config (its resumable overrides), then the checkpoint's state
        algo.restore_from_path(str(checkpoint_path(out_dir).resolve()))
    return algo


def _raise_stop(signum, frame):
    raise Stop()


def _metrics_row(algo, result: dict, started: float, at_start: dict) -> dict[str, float]:
    c = algo.counters
    elapsed = max(time.perf_counter() - started, 1e-9)
    row = {"env_steps": c["env_steps"], "learner_updates": c["updates"], "episodes": c["episodes"],
           "env_steps_per_s": (c["env_steps"] - at_start["env_steps"]) / elapsed,
           "learner_updates_per_s": (c["updates"] - at_start["updates"]) / elapsed,
           "seconds": elapsed, "training_iteration": result.get("training_iteration", 0)}
    for key in FAULT_COUNTERS:  # the formation path's failure record (docs/FAULTS.md)
        if key in c:
            row[f"faults/{key}"] = c[key]
    row.update({f"explore/{k}": v for k, v in flatten(result.get("explore", {})).items()})
    row.update({f"greedy/{k}": v for k, v in flatten(algo.last_eval).items()})
    learner = result.get("learners", {})
    for module, values in learner.items():
        if isinstance(values, dict):
            for key, name in LEARNER_METRICS.items():
                if key in values:
                    row[f"learner/{module}/{name}"] = float(values[key])
    return row
