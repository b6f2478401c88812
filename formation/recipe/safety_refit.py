"""Refitting a trained team's safety heads (``formation refit``): many fresh states of the team's own play,
labelled by the clairvoyant planner, fitted by the heads alone.

During training a safety head (``teacher.safety_horizon``) learns from the states in the replay, a few
hundred thousand at most, each seen by a learner that is also busy with the Q-values. Its wrong verdicts on
unseen states are what the trained teams fail on (docs/lab/TRAINING.md). After training, states cost far less:
the team plays thousands of games at once (``formation.evaluate.play_greedy``), the planner labels their
states in worker processes, and only the heads and their own encoders learn, by the learner's binary
cross-entropy. Each round plays the team as it is then, behind its refitted heads, so later rounds see the
states the refitted team visits (DAgger over the veto). The Q-values are not touched, so the team's way
to the destination stays as trained.

The states are kept as the networks' layers with weights read them (``DuelingQNetwork.prepare``: the window
around the leader of the screen read per cell, with the forecast planes), whose entries are all 0 or 1: one
bit each, 756 bytes a state on the paper's settings.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import pickle
import shutil
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from formation.config import ConfigError, GameConfig
from formation.evaluate import play_greedy
from formation.planner import surviving_first_moves_many
from formation.recipe.config import REFIT_GAMES_PER_SEED, RefitSettings
from formation.recipe.qnet import N_ACTIONS, DuelingQNetwork

LABEL_CHUNK = 256  # scenarios per planner call: small enough for its dense deduplication (planner.py)
JOINT = N_ACTIONS * N_ACTIONS


class StateBank:
    """States as the networks' layers with weights read them (``DuelingQNetwork.prepare``'s output: the
    game's screens and grids, the forecast planes and the board plane are all 0 or 1), eight to a byte."""

    def __init__(self) -> None:
        self.parts: list[np.ndarray] = []
        self.shape: tuple[int, int, int] | None = None  # (H, W, C) of a prepared state
        self._joined: np.ndarray | None = None

    def add(self, prepared: torch.Tensor) -> None:
        """Keep ``prepared`` (N, C, H, W) floats, each 0 or 1."""
        rows = prepared.permute(0, 2, 3, 1)  # what channels-last memory holds, entry by entry
        ones = rows > 0.5
        if not torch.where(ones, (rows - 1).abs() < 1e-5, rows == 0).all():
            raise ValueError("StateBank: prepared entries other than 0 and 1")
        self.shape = tuple(rows.shape[1:])
        self.parts.append(np.packbits(ones.reshape(len(rows), -1).numpy(), axis=1))
        self._joined = None

    def __len__(self) -> int:
        return sum(len(p) for p in self.parts)

    @property
    def nbytes(self) -> int:
        return sum(p.nbytes for p in self.parts)

    @classmethod
    def of_bits(cls, bits: np.ndarray, shape: tuple[int, int, int]) -> StateBank:
        """A bank of the states ``bits()`` gave (a kept refit's)."""
        bank = cls()
        bank.parts, bank.shape = [bits], tuple(shape)
        return bank

    def bits(self) -> np.ndarray:
        """Every state, one row of packed bits each."""
        if self._joined is None:
            self._joined = np.concatenate(self.parts) if len(self.parts) > 1 else self.parts[0]
            self.parts = [self._joined]
        return self._joined

    def batch(self, idx: np.ndarray) -> torch.Tensor:
        """The states ``idx`` as ``prepare`` gave them, (len(idx), C, H, W) floats in channels-last memory."""
        bits = np.unpackbits(self.bits()[idx], axis=1, count=int(np.prod(self.shape)))
        return torch.from_numpy(bits.reshape(len(idx), *self.shape)).float().permute(0, 3, 1, 2)


def label_states(scenarios: list, config: GameConfig, horizon: int) -> np.ndarray:
    """(N, 16) bool: the joint moves (leader's, follower's) that start ``horizon`` steps free of
    collisions and breaks (or a success sooner), from the planner, in chunks."""
    masks = np.concatenate([surviving_first_moves_many(scenarios[i:i + LABEL_CHUNK], config=config,
                                                       horizon=horizon)
                            for i in range(0, len(scenarios), LABEL_CHUNK)]) if scenarios else np.zeros(0, np.uint64)
    return ((masks[:, None] >> np.arange(JOINT, dtype=np.uint64)) & np.uint64(1)).astype(bool)


def _label_part(config_values: dict, scenarios: list, horizon: int) -> np.ndarray:
    """``label_states`` in a worker process."""
    return label_states(scenarios, GameConfig.from_dict(config_values), horizon)


@dataclass
class Gathered:
    """The states of a round's play and their labels (filled in by the planner's workers)."""

    states: int = 0
    success: list[float] = field(default_factory=list)
    labels: list[list[Future]] = field(default_factory=list)  # per part, its chunks' labels


def gather(policy, bank: StateBank, episodes: int, seed: int, epsilon: float, rng: np.random.Generator,
           label: Callable[[list], list[Future]], progress: Callable[[int, int], None] | None = None) -> Gathered:
    """Play ``episodes`` games of the team behind its heads' veto, with a random joint move in an
    ``epsilon`` share of the steps, in parts of ``REFIT_GAMES_PER_SEED`` games of seeds ``seed``, ``seed + 1``, ...;
    every state of every live game goes into ``bank``, and ``label(scenarios)`` is asked for its labels
    part by part (a worker may label one part while the next one plays); ``progress(games, states)`` after
    each part."""
    out = Gathered()
    seen: dict = {}
    key = policy.networks[policy.agent_modules[0]].prepare_key

    def act(obs: np.ndarray) -> np.ndarray:
        prepared: dict = {}
        actions = policy.act_batch_and_q(obs, prepared)[0]
        seen["prepared"] = prepared[key]
        noisy = rng.random(len(obs)) < epsilon
        actions[noisy] = rng.integers(0, N_ACTIONS, size=(int(noisy.sum()), actions.shape[1]))
        return actions

    for part, start in enumerate(range(0, episodes, REFIT_GAMES_PER_SEED)):
        scenarios: list = []

        def watch(game, actions, live, scenarios=scenarios) -> None:
            idx = np.flatnonzero(live)
            bank.add(seen["prepared"][torch.from_numpy(idx)])
            scenarios.extend(game.scenario(int(i)) for i in idx)

        games = min(REFIT_GAMES_PER_SEED, episodes - start)
        played = play_greedy(policy.game, act, games, seed + part, watch=watch)
        out.success.append(played["summary"]["success"])
        out.labels.append(label(scenarios))
        out.states += len(scenarios)
        if progress is not None:
            progress(start + games, out.states)
    return out


def safety_parameters(net: DuelingQNetwork) -> list[torch.nn.Module]:
    """What a refit trains of a network: its safety head, and the head's own encoder where it has one (a
    head on the Q-values' features learns alone, so that the Q-values stay as trained)."""
    if net.safety is None:
        return []
    return [net.safety] + ([net.safety_encoder] if net.safety_encoder is not None else [])


def verdict_errors(networks: dict[str, DuelingQNetwork], bank: StateBank, safe: np.ndarray,
                   batch: int = 2048) -> dict[str, int]:
    """How often the heads' verdict (their mean probability above one half, as greedy play reads it)
    disagrees with the planner's ``safe`` on the states of ``bank``."""
    counts = {"unsafe_judged_safe": 0, "unsafe": 0, "safe_judged_unsafe": 0, "safe": 0}
    heads = [net for net in networks.values() if net.safety is not None]
    for start in range(0, len(safe), batch):
        idx = np.arange(start, min(start + batch, len(safe)))
        x = bank.batch(idx)
        with torch.no_grad():
            probability = torch.stack([torch.sigmoid(net.safety_logits(x)) for net in heads]).mean(0)
        judged, truth = (probability > 0.5).numpy(), safe[idx]
        counts["unsafe_judged_safe"] += int((judged & ~truth).sum())
        counts["unsafe"] += int((~truth).sum())
        counts["safe_judged_unsafe"] += int((~judged & truth).sum())
        counts["safe"] += int(truth.sum())
    return counts


def heads_optimizer(networks: dict[str, DuelingQNetwork], lr: float) -> torch.optim.Optimizer:
    """Adam over every ``safety_parameters``, in one fixed order (a kept optimizer state loads into it)."""
    return torch.optim.Adam([p for net in networks.values() for m in safety_parameters(net) for p in m.parameters()],
                            lr=lr)


def fit(networks: dict[str, DuelingQNetwork], bank: StateBank, safe: np.ndarray, updates: int, lr: float,
        batch_size: int, rng: np.random.Generator, optimizer: torch.optim.Optimizer | None = None,
        progress: Callable[[int, int, float], None] | None = None) -> tuple[torch.optim.Optimizer, float]:
    """``updates`` steps of Adam on every head's binary cross-entropy against ``safe`` (N, 16), batches drawn
    uniformly from ``bank``; only ``safety_parameters`` learn. Returns the optimizer (to go on with) and the
    mean loss of the last updates."""
    modules = [m for net in networks.values() for m in safety_parameters(net)]
    if optimizer is None:
        optimizer = heads_optimizer(networks, lr)
    for m in modules:
        m.requires_grad_(True)
        m.train()
    target = torch.from_numpy(safe)
    recent: list[float] = []
    try:
        for u in range(updates):
            idx = rng.integers(0, len(safe), batch_size)
            x, y = bank.batch(idx), target[idx].float()
            loss = torch.zeros(())
            for net in networks.values():
                if net.safety is not None:
                    loss = loss + torch.nn.functional.binary_cross_entropy_with_logits(net.safety_logits(x), y)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            recent = (recent + [loss.item()])[-100:]
            if progress is not None and (u + 1) % 500 == 0:
                progress(u + 1, updates, float(np.mean(recent)))
    finally:
        for m in modules:
            m.eval()
            m.requires_grad_(False)
    return optimizer, float(np.mean(recent)) if recent else math.nan


def check_refittable(policy, name: str | None = None) -> None:
    """A one-line ``ConfigError`` unless ``refit`` can work on ``policy`` (called ``name``, else by its source):
    one follower, and networks that read their observations alike."""
    name = name or policy.source
    if policy.game.n_followers != 1:
        raise ConfigError(f"refit: {name} has {policy.game.n_followers} followers; allowed: one (the safety heads "
                          "judge the joint moves of a leader and one follower)")
    keys = {policy.networks[m].prepare_key for m in policy.agent_modules}
    if len(keys) > 1:
        raise ConfigError(f"refit: {name}'s networks read their observations differently; "
                          "allowed: networks that prepare alike (as training builds them)")


def add_safety_heads(policy) -> list[str]:
    """Give each network of ``policy`` that has none a safety head on an encoder of its own, that encoder a copy
    of the trained one the Q-values read, so that the head starts from features that already see the
    obstacles; the head's own layers start fresh. Until they are fitted the team plays without its veto.
    Returns the modules that got heads."""
    added = []
    for module, net in sorted(policy.networks.items()):
        if net.safety is not None:
            continue
        spec = dataclasses.replace(net.spec, safety=True, safety_encoder=True)
        grown = spec.build()
        grown.load_state_dict(net.state_dict(), strict=False)  # every weight it had; the head's are new
        grown.safety_encoder[0].load_state_dict(net.encoder.state_dict())
        grown.eval()
        grown.requires_grad_(False)
        policy.networks[module], policy.specs[module] = grown, spec
        added.append(module)
    if added:
        policy.learned_veto = False
    return added


def refit(policy, settings: RefitSettings, say: Callable[[str], None] = print, keep: Path | None = None) -> dict:
    """Refit ``policy``'s safety heads in place (``RefitSettings``), first adding them where it has none
    (``add_safety_heads``), and set its ``veto_threshold``; the report of every round.

    With ``keep`` (a folder), each finished round leaves there all that the next ones need, and a refit of the
    same ``policy`` and settings (more or fewer ``rounds`` aside) that finds it goes on after that round, to
    the same heads an unbroken refit makes: a stopped run loses at most the round in progress."""
    check_refittable(policy)
    added = add_safety_heads(policy)
    if added:
        say(f"safety heads added to {', '.join(added)} (their encoders copied from the Q-values'); the team plays "
            "without its veto until they are first fitted")
    config = policy.game
    networks = {m: policy.networks[m] for m in sorted(set(policy.agent_modules))}
    workers = settings.workers or os.cpu_count() or 1
    rng = np.random.default_rng(settings.seed)
    started = time.monotonic()

    def minutes() -> str:
        return f"{(time.monotonic() - started) / 60:.1f} min"
    report: dict = {"settings": {k: getattr(settings, k) for k in settings.__dataclass_fields__}, "rounds": [],
                    "heads_added": added}
    team = team_digest(networks)
    kept = kept_rounds(keep, settings, team, say) if keep is not None else None
    import multiprocessing

    context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        def label(scenarios: list) -> list[Future]:
            step = max(LABEL_CHUNK, math.ceil(len(scenarios) / workers / LABEL_CHUNK) * LABEL_CHUNK)
            return [pool.submit(_label_part, config.to_dict(), scenarios[i:i + step], settings.horizon)
                    for i in range(0, len(scenarios), step)]

        def labels_of(gathered: Gathered) -> np.ndarray:
            parts = [f.result() for futures in gathered.labels for f in futures]
            return np.concatenate(parts) if parts else np.zeros((0, JOINT), bool)

        holdout_bank, holdout_safe = StateBank(), None
        bank, safe_parts, optimizer, first = StateBank(), [], None, 0
        if kept is not None:
            first, optimizer = kept["round"], heads_optimizer(networks, settings.lr)
            for module, net in networks.items():
                for part, state in zip(safety_parameters(net), kept["heads"][module]):
                    part.load_state_dict(state)
            optimizer.load_state_dict(kept["optimizer"])
            rng.bit_generator.state = kept["rng"]
            started -= kept["seconds"]
            report = {**kept["report"], "settings": report["settings"]}
            bank, safe_parts = kept["bank"], [kept["safe"]]
            holdout_bank, holdout_safe = kept["holdout_bank"], kept["holdout_safe"]
            policy.learned_veto = True
            say(f"refit: round(s) 1-{first} kept in {keep}; going on from there")
        elif settings.holdout_episodes:
            # seeds below the refit's own: the held-out games never overlap the ones it learns from
            held = gather(policy, holdout_bank, settings.holdout_episodes,
                          settings.seed - math.ceil(settings.holdout_episodes / REFIT_GAMES_PER_SEED),
                          settings.epsilon, rng, label)
            holdout_safe = labels_of(held)
            before = verdict_errors(networks, holdout_bank, holdout_safe)
            report["holdout"] = {"states": len(holdout_bank), "before": before}
            say(f"held-out states: {len(holdout_bank):,}; the heads' wrong verdicts before: "
                f"{_errors_line(before)}")
        for round_ in range(first, settings.rounds):
            t0 = time.monotonic()
            seed = settings.seed + round_ * math.ceil(settings.episodes / REFIT_GAMES_PER_SEED)
            gathered = gather(policy, bank, settings.episodes, seed, settings.epsilon, rng, label,
                              lambda games, states: say(f"  played {games:,}/{settings.episodes:,} games, {states:,} "
                                                        f"states ({minutes()})"))
            played = time.monotonic() - t0
            safe_parts.append(labels_of(gathered))
            safe = np.concatenate(safe_parts)
            labelled = time.monotonic() - t0 - played
            updates = max(1, round(settings.epochs * len(safe) / settings.batch_size))
            say(f"round {round_ + 1}/{settings.rounds}: {gathered.states:,} states from {settings.episodes:,} "
                f"games (success with epsilon {settings.epsilon:g}: {np.mean(gathered.success):.1%}), "
                f"{len(safe):,} in all ({bank.nbytes / 2**20:,.0f} MiB); played in {played:.0f} s, labelled over "
                f"{settings.horizon} steps {labelled:.0f} s after; fitting {updates:,} updates")

            def progress(done: int, total: int, loss: float) -> None:
                if done % 2000 == 0 or done == total:
                    say(f"  update {done:,}/{total:,}: loss {loss:.5f} ({minutes()})")
            t1 = time.monotonic()
            optimizer, loss = fit(networks, bank, safe, updates, settings.lr, settings.batch_size, rng, optimizer,
                                  progress)
            policy.learned_veto = True  # the next round plays behind the heads as they are now
            entry = {"round": round_ + 1, "states": gathered.states, "states_in_all": len(safe),
                     "play_success": float(np.mean(gathered.success)), "updates": updates, "loss": loss,
                     "seconds": {"play": played, "label": labelled, "fit": time.monotonic() - t1}}
            if holdout_safe is not None:
                entry["holdout"] = verdict_errors(networks, holdout_bank, holdout_safe)
            report["rounds"].append(entry)
            if keep is not None:
                keep_round(keep, round_ + 1, settings, team, networks, optimizer, rng, bank, safe, holdout_bank,
                           holdout_safe, report, time.monotonic() - started)
            say(f"round {round_ + 1}/{settings.rounds} done in {time.monotonic() - t0:.0f} s: loss {loss:.5f}"
                + (f"; held-out wrong verdicts: {_errors_line(entry['holdout'])}" if holdout_safe is not None else ""))
    policy.veto_threshold, policy.veto_fallback = settings.veto_threshold, settings.veto_fallback
    report["seconds"] = time.monotonic() - started
    return report


def _lasting(settings: RefitSettings) -> dict:
    """The settings a finished round depends on: all but how many rounds follow, the labels' processes
    and the veto the finished team plays with."""
    return {k: getattr(settings, k) for k in settings.__dataclass_fields__
            if k not in ("rounds", "workers", "veto_threshold", "veto_fallback")}


def team_digest(networks: dict[str, DuelingQNetwork]) -> str:
    """A fingerprint of what a refit does not change (all but the safety heads and their encoders): rounds kept
    for one trained team are no start for another, such as the same run trained further."""
    digest = hashlib.sha256()
    for module, net in sorted(networks.items()):
        for name, value in sorted(net.state_dict().items()):
            if not name.startswith(("safety.", "safety_encoder.")):
                digest.update(f"{module}.{name}".encode())
                digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def keep_round(keep: Path, round_: int, settings: RefitSettings, team: str, networks: dict[str, DuelingQNetwork],
               optimizer: torch.optim.Optimizer, rng: np.random.Generator, bank: StateBank, safe: np.ndarray,
               holdout_bank: StateBank, holdout_safe: np.ndarray | None, report: dict, seconds: float) -> None:
    """All that the rounds after ``round_`` need, in ``keep/round<round_>``; its ``state.pt`` comes last, so that
    a folder holding one is whole; the earlier rounds' folders go once it is there."""
    folder = keep / f"round{round_}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    np.save(folder / "bank.npy", bank.bits())
    np.save(folder / "safe.npy", safe)
    if holdout_safe is not None:
        np.save(folder / "holdout.npy", holdout_bank.bits())
        np.save(folder / "holdout_safe.npy", holdout_safe)
    state = {"round": round_, "settings": _lasting(settings), "team": team, "seconds": seconds, "report": report,
             "rng": rng.bit_generator.state, "optimizer": optimizer.state_dict(), "shape": bank.shape,
             "heads": {m: [part.state_dict() for part in safety_parameters(net)] for m, net in networks.items()}}
    torch.save(state, folder / "state.pt.new")
    os.replace(folder / "state.pt.new", folder / "state.pt")
    for earlier in keep.glob("round*"):
        if earlier != folder:
            shutil.rmtree(earlier, ignore_errors=True)


def kept_rounds(keep: Path, settings: RefitSettings, team: str, say: Callable[[str], None]) -> dict | None:
    """What ``keep_round`` left in ``keep`` after the last whole round, or None where nothing was kept or it was
    kept with other settings or for another ``team`` (then it is removed, and the refit starts over)."""
    whole = [f for f in keep.glob("round*") if f.name[5:].isdigit() and (f / "state.pt").is_file()]
    if not whole:
        return None
    folder = max(whole, key=lambda f: int(f.name[5:]))
    why = None
    try:
        state = torch.load(folder / "state.pt", weights_only=False)  # written by keep_round: numbers and tensors
        if state["settings"] != _lasting(settings) or state["round"] > settings.rounds or state["team"] != team:
            why = "were made with other settings or for another team"
        else:
            state["bank"] = StateBank.of_bits(np.load(folder / "bank.npy"), state["shape"])
            state["safe"] = np.load(folder / "safe.npy")
            held = (folder / "holdout_safe.npy").is_file()
            state["holdout_bank"] = StateBank.of_bits(np.load(folder / "holdout.npy"), state["shape"]) if held \
                else StateBank()
            state["holdout_safe"] = np.load(folder / "holdout_safe.npy") if held else None
            if len(state["safe"]) != len(state["bank"]):
                raise ValueError("states and labels differ")
    except (OSError, EOFError, ValueError, RuntimeError, KeyError, pickle.UnpicklingError) as error:
        why = f"could not be read ({type(error).__name__}: {error})"
    if why is not None:
        say(f"refit: the round(s) kept in {keep} {why}; starting over")
        shutil.rmtree(keep, ignore_errors=True)
        return None
    return state


def _errors_line(counts: dict[str, int]) -> str:
    return (f"unsafe judged safe {counts['unsafe_judged_safe']:,}/{counts['unsafe']:,}, "
            f"safe judged unsafe {counts['safe_judged_unsafe']:,}/{counts['safe']:,}")
