"""The recipe in one process, top to bottom, without Ray: collect, store, learn, evaluate.

    formation train CONFIG --no-ray --out DIR
    # or, from Python:
    from formation.recipe.config import RunConfig
    from formation.recipe.loop import train
    summary = train(RunConfig.load("configs/small.yaml"), "runs/small")

It runs the very functions of the distributed path (the rollout actors' ``Collector``, the replay actors'
``FrameReplay``, the learner's ``Learner``: ``forward`` and ``dqn_loss``), one after the other, on one core: the
reference a reader can follow, and what the learning tests train with. The folder it writes holds ``config.yaml``,
``metrics.jsonl`` (a line per evaluation), ``result.json`` (the final greedy evaluation) and the team as an export
(``policy.json``, ``<module>.pt``; written at every evaluation, so a stopped run leaves the team it last
evaluated; with ``train.average_decay``, the averaged team that training evaluates), which ``formation evaluate
DIR`` and ``formation.policy.load(DIR)`` read, in ``best/`` the team of the best evaluation so far
(``formation.policy.keep_if_best``), and ``checkpoint.pt``: the networks, target copies, averages, optimizers and
counters, at every evaluation, every 10 minutes and on Ctrl-C or SIGTERM (the round under way ends first; a second
signal stops at once), from which ``formation train --no-ray --resume --out DIR`` goes on. As on the distributed
path, the replay is not kept: a resumed run refills it and skips the updates owed meanwhile.
"""

from __future__ import annotations

import copy
import json
import pickle
import signal
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from formation.config import ConfigError
from formation.evaluate import play_greedy
from formation.policy import Policy, export, keep_if_best
from formation.recipe.collect import Collector, epsilon_at
from formation.recipe.config import RunConfig
from formation.recipe.learn import Learner
from formation.recipe.qnet import tied
from formation.recipe.replay import FrameReplay
from formation.recipe.team import module_of_agent, network_specs, replay_frame_shape

CHECKPOINT = "checkpoint.pt"  # the run's state to go on from (--resume); written at every evaluation
CHECKPOINT_SECONDS = 600  # and at least this often: a stop loses little


@dataclass
class Game:
    """One game the team plays and learns from (a run plays one, or each of its ``games``): its run, rollouts,
    replay, and the team's networks and target networks reading its board (the weights are every game's)."""

    run: RunConfig
    collector: Collector
    replay: FrameReplay
    networks: dict[str, torch.nn.Module]
    targets: dict[str, torch.nn.Module]
    averaged: dict[str, torch.nn.Module] | None = None  # their moving average (train.average_decay)

    @property
    def team(self) -> dict[str, torch.nn.Module]:
        """The networks that are evaluated and exported: the average where the run keeps one."""
        return self.averaged or self.networks

    @property
    def name(self) -> str:
        return f"setting{self.run.game.setting}_followers{self.run.game.n_followers}"


def train(run: RunConfig, out: str | Path | None = None, say: Callable[[str], None] = print,
          record: dict | None = None, resume: bool = False) -> dict:
    """Train the team of ``run`` for ``train.total_env_steps`` env steps; the final greedy evaluation's summary
    (``formation.evaluate.play_greedy``; with ``games``, each game's and their mean success). With ``out``, the run
    folder described above; ``record`` joins the card's training section (the CLI's hardware and commit). With
    ``resume``, go on from ``out``'s checkpoint."""
    # -- boilerplate: seeding, the run folder, and the checkpoint to go on from
    t = run.train
    torch.manual_seed(t.seed)
    torch.set_num_threads(1)  # one core, as a rollout actor or a CPU learner of the distributed path has
    out = Path(out) if out is not None else None
    saved = load_checkpoint(out) if resume else None
    if saved is not None and saved["env_steps"] >= t.total_env_steps:
        raise ConfigError(f"--resume: the run has trained its {saved['env_steps']:,} env steps; allowed: --set "
                          f"train.total_env_steps=N with N above {saved['env_steps']}")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.yaml").write_text(yaml.safe_dump(run.to_dict(), sort_keys=False))
        metrics = (out / "metrics.jsonl").open("a" if resume else "w")

    # -- the team's networks, the learner, and each game's rollouts and replay (a share of the capacity)
    kinds = run.kinds()
    networks = {module: spec.build() for module, spec in network_specs(kinds[0]).items()}
    learner = Learner(kinds[0], networks)
    games = []
    for index, kind in enumerate(kinds):
        specs = network_specs(kind)
        replay = FrameReplay(t.replay_capacity // len(kinds), replay_frame_shape(kind), 1 + kind.game.n_followers,
                             kind.game.frame_stack, seed=t.seed + index, prioritized=t.prioritized)
        games.append(Game(kind, Collector(kind, index), replay,
                          *(reading(specs, nets, own=not index)
                            for nets in (networks, learner.targets, learner.averaged))))
    steps_per_collect = run.resources.games_per_actor * t.steps_per_sample
    # skipped: the updates owed while a resumed run's replay refilled, never run (as on the distributed path)
    env_steps, next_eval, skipped, seconds, sessions = 0, run.eval.every_env_steps, 0.0, 0.0, []
    if saved is not None:
        learner.load_state_dict(saved["learner"])
        env_steps, next_eval, skipped, seconds, sessions = (saved[k] for k in (
            "env_steps", "next_eval", "skipped", "seconds", "sessions"))
        say(f"resumed at {env_steps:,} env steps, {learner.updates:,} updates; the replay refills first")
    # the sessions' records as plain values, which torch.load reads with weights_only
    sessions = [*sessions, json.loads(json.dumps(record or {}, default=str))]
    started, saved_at, stats, episodes = time.perf_counter() - seconds, time.perf_counter(), {}, []

    with deferred_stop(say) as stop:
        while env_steps < t.total_env_steps and not stop:
            # -- collect: every game plays steps_per_sample steps, epsilon-greedily (the teacher labels them, if any)
            for game in games:
                records, ended = game.collector.collect(game.networks, t.steps_per_sample, env_steps)
                game.replay.add(records)
                env_steps += steps_per_collect
                episodes += ended

            # -- learn: the updates the replay ratio owes (updates per env step), from learning_starts on, each on
            # a sample of the next game in turn
            if all(g.replay.size >= max(t.learning_starts // len(games), t.batch_size) for g in games):
                while learner.updates < t.replay_ratio * env_steps - skipped:
                    game = games[learner.updates % len(games)]
                    sample = game.replay.sample(t.batch_size, n_step=t.n_step, gamma=t.gamma)
                    priorities, stats = learner.update(sample, (module_of_agent(game.run), game.networks,
                                                                game.targets))
                    if t.prioritized:
                        game.replay.update_priorities(sample["ids"], priorities)
            elif learner.updates:
                skipped = t.replay_ratio * env_steps - learner.updates

            # -- evaluate: greedy play on held-out scenarios, every eval.every_env_steps
            evaluated = env_steps >= next_eval or env_steps >= t.total_env_steps
            if evaluated:
                summary = evaluate_games(games)
                row = {"env_steps": env_steps, "learner_updates": learner.updates,
                       "seconds": time.perf_counter() - started, "epsilon": epsilon_at(env_steps, t),
                       **{f"greedy/{k}": summary[k] for k in ("success", "steps_success_mean") if k in summary},
                       **{f"greedy/{name}/success": s["success"] for name, s in summary.get("games", {}).items()},
                       **{f"learner/{m}/{k}": v for m, values in stats.items() for k, v in values.items()},
                       **explored(episodes)}
                episodes, kept = [], False
                if out is not None:  # the team as evaluated, so that a run stopped later still leaves it
                    metrics.write(json.dumps(row) + "\n")
                    metrics.flush()
                    team = policy_of(kinds[0], games[0].team, source=str(out), env_steps=env_steps)
                    team.training = {"config": run.to_dict(), "env_steps": env_steps,
                                     "learner_updates": learner.updates, "wall_seconds": round(row["seconds"], 3),
                                     "evaluation": {"env_steps": env_steps, "seed": run.eval.seed, "greedy": summary},
                                     **sessions[-1], **({"sessions": sessions} if len(sessions) > 1 else {})}
                    export(team, out)
                    kept = keep_if_best(team, out)
                say(f"{env_steps:>9,}/{t.total_env_steps:,} env steps  greedy success {summary['success']:6.1%}  "
                    f"{env_steps / row['seconds']:6,.0f} env steps/s" + ("  (best so far: best/)" if kept else ""))
                next_eval += run.eval.every_env_steps

            # -- checkpoint: at every evaluation, every CHECKPOINT_SECONDS, and when stopped
            if out is not None and (evaluated or stop or time.perf_counter() - saved_at > CHECKPOINT_SECONDS):
                save_checkpoint(out, {"learner": learner.state_dict(), "env_steps": env_steps, "next_eval": next_eval,
                                      "skipped": skipped, "seconds": time.perf_counter() - started,
                                      "sessions": sessions})
                saved_at = time.perf_counter()

    # -- boilerplate: the final evaluation's result (the team is exported with it, above)
    if out is not None:
        metrics.close()
    if stop:
        say(f"stopped at {env_steps:,} env steps" + (f": checkpoint saved in {out / CHECKPOINT}; continue with "
                                                      f"formation train --no-ray --resume --out {out}" if out else ""))
        raise KeyboardInterrupt
    if out is not None:
        (out / "result.json").write_text(json.dumps({"env_steps": env_steps, "seed": run.eval.seed,
                                                     "greedy": summary}, indent=2))
    return summary


def save_checkpoint(out: Path, state: dict) -> None:
    """``out/checkpoint.pt``, replaced whole (written beside it, then renamed), so a run stopped while it writes
    keeps the one before."""
    torch.save(state, out / (CHECKPOINT + ".partial"))
    (out / (CHECKPOINT + ".partial")).replace(out / CHECKPOINT)


def load_checkpoint(out: Path) -> dict:
    try:
        return torch.load(out / CHECKPOINT)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as err:
        raise ConfigError(f"--resume: {str(out / CHECKPOINT)!r} cannot be read ({type(err).__name__}); allowed: "
                          "the checkpoint.pt a --no-ray run wrote") from None


@contextmanager
def deferred_stop(say: Callable[[str], None]):
    """A list that a SIGINT (Ctrl-C) or SIGTERM joins, instead of stopping the loop where it is: the loop ends its
    round and saves its checkpoint first. A second signal stops at once, from the checkpoint before. Outside the
    main thread, signals stop nothing here."""
    stop: list[int] = []

    def defer(signum: int, frame) -> None:
        if stop:
            raise KeyboardInterrupt
        stop.append(signum)
        say("stopping once this round is saved (again to stop now, from the checkpoint before)")

    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    before = {s: signal.signal(s, defer) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def reading(specs: dict, networks: dict[str, torch.nn.Module] | None, own: bool) -> dict | None:
    """``networks`` reading the board of ``specs``: themselves on the run's ``own`` (first) game, else networks
    tied to them (``formation.recipe.qnet.tied``)."""
    if networks is None or own:
        return networks
    return {m: tied(specs[m], net) for m, net in networks.items()}


def policy_of(run: RunConfig, networks: dict[str, torch.nn.Module], source: str, env_steps: int | None = None):
    """A ``formation.policy.Policy`` of copies of ``networks`` (a Policy freezes the networks it holds)."""
    return Policy(run.game, {m: copy.deepcopy(net) for m, net in networks.items()}, network_specs(run),
                  module_of_agent(run), source=source, env_steps=env_steps,
                  eval_settings={"episodes": run.eval.episodes, "seed": run.eval.seed})


def evaluate(run: RunConfig, networks: dict[str, torch.nn.Module]) -> dict:
    """Greedy play of the team as it is now on ``eval.episodes`` held-out scenarios: the summary rates."""
    team = policy_of(run, networks, source="training")
    return play_greedy(run.game, team.act_batch, run.eval.episodes, run.eval.seed)["summary"]


def evaluate_games(games: list[Game]) -> dict:
    """``evaluate`` of one game; of several, each game's summary (``games``, by name) and their mean success."""
    if len(games) == 1:
        return evaluate(games[0].run, games[0].team)
    each = {g.name: evaluate(g.run, g.team) for g in games}
    return {"success": float(np.mean([s["success"] for s in each.values()])), "games": each}


def explored(episodes: list[dict]) -> dict[str, float]:
    """The training episodes' rates (exploring, so below greedy play), as ``explore/<key>``."""
    if not episodes:
        return {}
    return {f"explore/{key}": float(np.mean([e[key] for e in episodes]))
            for key in ("success", "collided", "broken", "truncated")}
