"""Trained policies outside training: restore a run's greedy team from its checkpoint or from an export.

    policy = load("runs/s1")             # a run folder of `formation train`: its final team
    policy = load("runs/s1/checkpoint")  # the checkpoint inside one: the networks as trained
    policy = load(result.checkpoint.path)  # a Tune trial's checkpoint (it holds its run's config.yaml)
    policy = load("exports/s1")          # a folder written by `formation export` (policy.json, <module>.pt)

    env = formation.env.parallel_env(**policy.env_config)
    obs, _ = env.reset(seed=0)
    obs, rewards, *_ = env.step(policy.act(obs))

A run's modules are read from ``checkpoint/learner_group/learner/rl_module/<module>/module_state.pkl``
(plain numpy arrays) into the same ``DuelingQNetwork`` the RLlib module wraps, built from the run's
``config.yaml`` (the run folder's, or the copy every checkpoint holds) exactly as training builds it; no Ray
cluster is started. An export holds each module's ``q_network`` state dict (``<module>.pt``) and a card,
``policy.json``, with everything needed to rebuild the networks with torch alone. Greedy actions are the argmax
of the Q-values, as in training's greedy evaluation (``FormationDQN.play_greedy``).

The card's ``training`` section says how the team was trained (``Policy.training``): the whole resolved
run config, env steps and learner updates, wall time summed over ``--resume`` sessions, hardware, the
code's commit, each session (from the run's ``training.json``), and the greedy evaluation the run ended
with (its ``result.json``: env steps, seed, summary; None when the checkpoint is newer than it). Cards
written before it (format 1 without the section, as the shipped ``policies/``) load with ``training``
None; a run trained before ``training.json`` gives the config, counters and evaluation, the rest None.

Bad input (a missing path, a folder that is no checkpoint, a damaged file) raises ``PolicyError``,
a ``ConfigError`` with one line naming the problem.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import pickle
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from formation.config import ConfigError, GameConfig
from formation.recipe.config import VETO_FALLBACKS, RunConfig
from formation.recipe.qnet import N_ACTIONS, DuelingQNetwork, NetworkSpec, agent_roles, outputs_of, team_q_values
from formation.shield import Shield, shielded_moves

FORMAT_VERSION = 1
CARD = "policy.json"
# in a checkpoint folder (a run folder's checkpoint/, or a Tune trial's checkpoint_NNNNNN/)
RL_MODULES = Path("learner_group") / "learner" / "rl_module"
CHECKPOINT_STATE = "algorithm_state.pkl"  # the counters, among RLlib's own state
CHECKPOINT_CONFIG = "config.yaml"  # the run config, written with every checkpoint (FormationDQN.save_to_path)
# a run whose config has a refit phase keeps its final team here, as an export (``formation.train``)
REFITTED = "refitted"
# a run folder's team of its best greedy evaluation during training, as an export (``keep_if_best``)
BEST = "best"
DEFAULT_EVAL = {"episodes": 200, "seed": 1_000_000}
DEFAULT_VETO_THRESHOLD = 0.5  # what training's heads are fitted to: the better guess of safe or not
TRAINING = "training.json"  # a run folder's training record (``formation.train.training_record``)


class PolicyError(ConfigError):
    """A path that holds no usable policy: one line naming the path and what is wrong."""


class Policy:
    """The greedy team: one Q-network per module, and which agent acts with which module."""

    def __init__(self, game: GameConfig, networks: dict[str, DuelingQNetwork], specs: dict[str, NetworkSpec],
                 agent_modules: list[str], source: str, env_steps: int | None = None,
                 eval_settings: dict[str, int] | None = None):
        self.game = game
        self.networks = networks
        self.specs = specs
        self.agent_modules = list(agent_modules)
        self.source = source
        self.env_steps = env_steps
        self.eval_settings = dict(eval_settings or DEFAULT_EVAL)
        self.shield: Shield | None = None
        self.refit_report: dict | None = None  # what `formation refit` did to the safety heads, if it did
        self.training: dict | None = None  # how it was trained (the card's ``training``); None if not known
        # greedy play keeps to the joint moves whose mean safe probability is above this (``within_veto``)
        self.veto_threshold = DEFAULT_VETO_THRESHOLD
        self.veto_fallback = VETO_FALLBACKS[0]  # where no joint move is above it (``within_veto``)
        # networks with a safety head (teacher.safety_horizon) keep greedy play to the joint moves it judges safe
        self.learned_veto = any(net.safety is not None for net in networks.values())
        for net in networks.values():
            net.eval()
            net.requires_grad_(False)

    @property
    def agents(self) -> list[str]:
        return list(self.game.agent_names)

    @property
    def env_config(self) -> dict[str, Any]:
        """Keyword arguments of ``formation.env.parallel_env`` for the game the policy was trained on."""
        return self.game.to_dict()

    @property
    def module_of(self) -> dict[str, str]:
        return dict(zip(self.agents, self.agent_modules))

    def q_values(self, obs: np.ndarray, module: str) -> np.ndarray:
        """Q-values of one module for uint8 observations (N, h, w, c): (N, 4), or (N, 16) for a module
        that answers the leader (one per (leader's move, own move), row by row); (N, roles, ...) for a module
        several agents share (``NetworkSpec.roles``), each role's."""
        with torch.no_grad():
            return self.networks[module](torch.from_numpy(np.ascontiguousarray(obs))).numpy()

    def q_batch(self, obs: np.ndarray) -> np.ndarray:
        """Every agent's Q-values (N, 1+k, 4) for a batch of observations (N, h, w, c) every agent shares;
        each module runs once, whatever the number of agents using it. A follower that answers the
        leader reads the row of the leader's greedy move."""
        return team_q_values(self._q_by_module(obs), self.agent_modules)

    def _q_by_module(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {m: self.q_values(obs, m) for m in sorted(set(self.agent_modules))}

    def for_game(self, game: GameConfig | None = None, *, setting: int | None = None,
                 n_followers: int | None = None) -> Policy:
        """The same weights playing another game: ``game``, or this one on named ``setting`` and/or with
        ``n_followers`` (``GameConfig.variant``). Networks that look through the leader's window on a board read
        cell by cell (``train.leader_window``, and ``train.screen_cells`` on screens) read every board alike, and
        a follower network with roles plays a team of up to that many followers. Where the networks cannot read
        the game, a one-line ``PolicyError`` says why."""
        game = game if game is not None else self.game.variant(setting, n_followers)
        for key in ("obs_type", "frame_stack"):
            if getattr(game, key) != getattr(self.game, key):
                raise PolicyError(f"game.{key}: {getattr(game, key)!r} is not allowed; this policy reads "
                                  f"{getattr(self.game, key)!r}")
        board = (game.height, game.width)
        specs = {}
        for module, spec in self.specs.items():
            if spec.window is None or (game.obs_type == "pixels" and spec.cells is None):
                raise PolicyError(f"game: this policy's {module} network reads the whole {self.game.height}x"
                                  f"{self.game.width} board, not a window around the leader; it plays that board only")
            if game.obs_type == "pixels":
                specs[module] = dataclasses.replace(spec, cells=board)
            else:
                specs[module] = dataclasses.replace(spec, obs_shape=(*board, spec.obs_shape[2]))
        follower = self.agent_modules[1]
        roles = max(specs[follower].roles, 1)
        if game.n_followers > roles:
            raise PolicyError(f"game.n_followers: {game.n_followers} is not allowed; this policy's follower network "
                              f"plays 1 to {roles}")
        if game.n_followers > 1 and (self.learned_veto or self.shield is not None):
            raise PolicyError(f"game.n_followers: {game.n_followers} is not allowed with a safety head or a shield; "
                              "allowed: 1")
        networks = {m: spec.build() for m, spec in specs.items()}
        for module, net in networks.items():
            net.load_state_dict(self.networks[module].state_dict())
        twin = Policy(game, networks, specs, [self.agent_modules[0]] + [follower] * game.n_followers, self.source,
                      self.env_steps, self.eval_settings)
        for key in ("refit_report", "training", "veto_threshold", "veto_fallback", "learned_veto"):
            setattr(twin, key, getattr(self, key))
        twin.shield = None if self.shield is None else Shield(game, self.shield.horizon)
        return twin

    def shielded(self, horizon: int) -> Policy:
        """The same networks behind a safety shield that looks ``horizon`` steps ahead
        (``formation.shield``; 0: none)."""
        twin = copy.copy(self)
        twin.shield = None if horizon == 0 else Shield(self.game, horizon)
        return twin

    def without_learned_veto(self) -> Policy:
        """The same networks playing their greedy moves whatever their safety heads say."""
        twin = copy.copy(self)
        twin.learned_veto = False
        return twin

    def outputs(self, obs: np.ndarray, prepared: dict | None = None) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
        """Each module's Q-values and the probability (N, 4, 4) its safety heads give each joint move of being
        safe (their mean; None without heads), from one pass of each network: the layers without weights run
        once for the networks that prepare alike (``prepared``, if given, keeps what they gave, as
        ``outputs_of``)."""
        networks = {m: self.networks[m] for m in sorted(set(self.agent_modules))}
        with torch.no_grad():
            q, safe = outputs_of(networks, torch.from_numpy(np.ascontiguousarray(obs)), prepared)
        return {m: v.numpy() for m, v in q.items()}, None if safe is None else safe.numpy()

    def with_veto_threshold(self, threshold: float) -> Policy:
        """The same networks, their veto keeping to the joint moves above ``threshold`` (``within_veto``)."""
        if not (isinstance(threshold, int | float) and 0.0 <= threshold < 1.0):
            raise PolicyError(f"veto threshold: {threshold!r} is not allowed; allowed: a number in [0, 1)")
        twin = copy.copy(self)
        twin.veto_threshold = float(threshold)
        return twin

    def with_veto_fallback(self, fallback: str) -> Policy:
        """The same networks, their veto keeping, where no joint move is above the threshold, to those
        ``fallback`` names (``within_veto``)."""
        if fallback not in VETO_FALLBACKS:
            raise PolicyError(f"veto fallback: {fallback!r} is not allowed; allowed: {', '.join(VETO_FALLBACKS)}")
        twin = copy.copy(self)
        twin.veto_fallback = fallback
        return twin

    def learned_safe_moves(self, obs: np.ndarray) -> np.ndarray | None:
        """(N, leader's move, follower's move) bool: the joint moves the networks' safety heads judge safe, as
        their veto reads them (``within_veto`` at ``veto_threshold``); None without heads."""
        safe_probability = self.outputs(obs)[1]
        return None if safe_probability is None else self._veto(safe_probability)

    def _veto(self, safe_probability: np.ndarray) -> np.ndarray:
        """``within_veto`` at this policy's ``veto_threshold`` and ``veto_fallback``."""
        return within_veto(safe_probability, self.veto_threshold, self.veto_fallback)

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        """Greedy joint actions (N, 1+k) for a batch of observations (N, h, w, c) every agent shares
        (``formation.evaluate.play_greedy``'s ``act``); behind the shield where one is set, and within the
        joint moves the networks' safety heads judge safe where they have them (``learned_veto``)."""
        return self.act_batch_and_q(obs)[0]

    def act_batch_and_q(self, obs: np.ndarray, prepared: dict | None = None
                        ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """``act_batch``'s joint actions and each module's Q-values they came from (as ``outputs``
        gives them, and ``prepared`` keeps), from one pass of each network."""
        if self.shield is None and not self.learned_veto and prepared is None:
            by_module = self._q_by_module(obs)
            return team_q_values(by_module, self.agent_modules).argmax(axis=-1), by_module
        by_module, safe_probability = self.outputs(obs, prepared)
        allowed = self.shield.allowed(obs) if self.shield is not None else None
        learned = self._veto(safe_probability) if self.learned_veto and safe_probability is not None else None
        return greedy_within(by_module, self.agent_modules, allowed, learned), by_module

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, int]:
        """Greedy actions of the agents in ``observations`` (per-agent observations as the PettingZoo
        env returns them)."""
        unknown = [a for a in observations if a not in self.module_of]
        if unknown:
            raise ValueError(f"observations: unknown agent(s) {unknown}; this policy's agents: {self.agents}")
        if (self.shield is not None or self.learned_veto) and observations:  # one screen for all: one joint move
            joint = self.act_batch(np.asarray(next(iter(observations.values())))[None])[0]
            return {a: int(joint[self.agents.index(a)]) for a in observations}
        by_module: dict[str, list[str]] = {}
        for agent in observations:
            by_module.setdefault(self.module_of[agent], []).append(agent)
        actions: dict[str, int] = {}
        leader = self.agent_modules[0]
        role = dict(zip(self.agents, agent_roles(self.agent_modules)))
        for module, agents in by_module.items():
            x = np.stack([np.asarray(observations[a]) for a in agents])
            q = {module: self.q_values(x, module)}
            if q[module].ndim == 3:  # a network the agents share: each reads its own role's Q-values
                q[module] = q[module][np.arange(len(agents)), [role[a] for a in agents]]
            if q[module].shape[-1] != N_ACTIONS:  # it answers the leader's greedy move, from its own screen
                q[leader] = self.q_values(x, leader)
            for agent, action in zip(agents, team_q_values(q, [leader, module])[:, 1].argmax(-1).tolist()):
                actions[agent] = int(action)
        return {a: actions[a] for a in observations}

    def card(self) -> dict[str, Any]:
        """The export's ``policy.json``."""
        return {"format_version": FORMAT_VERSION, "game": self.game.to_dict(),
                "networks": {m: spec.to_dict() for m, spec in sorted(self.specs.items())},
                "agents": self.module_of, "source": self.source, "env_steps": self.env_steps,
                "eval": dict(self.eval_settings), "veto_threshold": self.veto_threshold,
                "veto_fallback": self.veto_fallback,
                **({"refit": self.refit_report} if self.refit_report else {}),
                **({"training": self.training} if self.training else {})}


def export(policy: Policy, out: str | Path, half: bool = False) -> Path:
    """Write ``<module>.pt`` (each q_network's state dict) and ``policy.json`` into ``out``.

    ``half`` stores the weights as float16, half the size (loading turns them back to float32):
    Q-values then differ from the checkpoint's in the third significant digit or so, and a greedy
    action only where two actions' Q-values are that close. Evaluate the export itself."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PolicyError(f"export: {str(out)!r} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    for module, net in sorted(policy.networks.items()):
        state = net.state_dict()
        if half:
            state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
        torch.save(state, out / f"{module}.pt")
    card = {**policy.card(), "weights_dtype": "float16" if half else "float32"}
    (out / CARD).write_text(json.dumps(card, indent=2) + "\n")
    return out


def replace_export(policy: Policy, out: str | Path, half: bool = False) -> Path:
    """``export`` into a fresh folder beside ``out``, then put it in the place of ``out``: a reader, or a run
    stopped meanwhile, finds the old team or the new one whole, never a mix."""
    out = _recover_replaced(Path(out))
    fresh, old = out.with_name(f"{out.name}.new"), out.with_name(f"{out.name}.old")
    for leftover in (fresh, old):  # what a run stopped while replacing left
        if leftover.exists():
            shutil.rmtree(leftover)
    export(policy, fresh, half=half)
    if out.exists():
        os.rename(out, old)
    os.rename(fresh, out)
    shutil.rmtree(old, ignore_errors=True)
    return out


def _recover_replaced(out: Path) -> Path:
    """After a stop between the two renames of ``replace_export``, the old team is ``<out>.old``: put it back."""
    old = out.with_name(f"{out.name}.old")
    if old.is_dir() and not out.exists():
        os.rename(old, out)
    return out


def best_success(run_dir: str | Path) -> float | None:
    """The greedy success of the team a run keeps in ``best/`` (``keep_if_best``); None before its first."""
    card = _json_object(_recover_replaced(Path(run_dir) / BEST) / CARD) or {}
    greedy = ((card.get("training") or {}).get("evaluation") or {}).get("greedy") or {}
    return greedy.get("success")


def keep_if_best(policy: Policy, run_dir: str | Path) -> bool:
    """Export ``policy`` to the run's ``best/`` where its training evaluation (``policy.training["evaluation"]``)
    succeeds at least as often as the team kept there; a tie goes to the later, longer-trained team. Whether it
    was kept. Runs of the reward alone swing by tens of points between evaluations (docs/RECIPE.md), so the
    last team is often not the best one trained."""
    success = policy.training["evaluation"]["greedy"]["success"]
    best = best_success(run_dir)
    if best is not None and success < best:
        return False
    replace_export(policy, Path(run_dir) / BEST)
    return True


def load(path: str | Path) -> Policy:
    """A run folder, the ``checkpoint/`` inside one, or an exported policy folder -> ``Policy``. A run folder
    whose training ended with a refit phase gives its refitted team (``refitted/``); its ``checkpoint/``, the
    networks as trained."""
    path = Path(path)
    if not path.exists():
        raise PolicyError(f"checkpoint: no such file or folder {str(path)!r}")
    if not path.is_dir():
        raise PolicyError(f"checkpoint: {str(path)!r} is a file; give a run folder (config.yaml, checkpoint/), "
                          f"its checkpoint/ folder, or an exported policy folder ({CARD})")
    if (path / CARD).is_file():
        return _load_export(path)
    if (path / "config.yaml").is_file() and (path / "checkpoint").is_dir():
        return _load_export(path / REFITTED) if (path / REFITTED / CARD).is_file() else _load_run(path)
    if path.name == "checkpoint" and (path.parent / "config.yaml").is_file():
        return _load_run(path.parent)
    if (path / CHECKPOINT_CONFIG).is_file() and (path / RL_MODULES).is_dir():  # a checkpoint on its own
        return _load_run(path, checkpoint=path)
    raise PolicyError(f"checkpoint: {str(path)!r} is not a checkpoint; give a run folder (config.yaml, "
                      f"checkpoint/), its checkpoint/ folder, a Tune trial's checkpoint folder, or an exported "
                      f"policy folder ({CARD})")


# ---------------------------------------------------------------------- run folders
def _load_run(run_dir: Path, checkpoint: Path | None = None) -> Policy:
    """A run folder's team (its ``checkpoint/``), or a checkpoint's on its own (``run_dir`` = ``checkpoint``)."""
    from formation.recipe.team import module_of_agent, network_specs

    checkpoint = checkpoint or run_dir / "checkpoint"
    try:
        run = RunConfig.load_saved(run_dir / "config.yaml")
    except ConfigError as err:
        raise PolicyError(f"checkpoint: {str(run_dir / 'config.yaml')!r}: {err}") from None
    specs, agent_modules = network_specs(run), module_of_agent(run)
    networks = {}
    for module, spec in specs.items():
        state_file = checkpoint / RL_MODULES / module / "module_state.pkl"
        if not state_file.is_file():
            raise PolicyError(f"checkpoint: {str(checkpoint / RL_MODULES)!r} has no module {module!r} "
                              f"(expected {str(state_file)!r}); the run may not have saved a checkpoint yet")
        try:
            with state_file.open("rb") as f:
                state = pickle.load(f)
            # the team training evaluated: the moving average of the weights where the run keeps one
            averaged = any(k.startswith("_averaged_q_network.") for k in state)
            prefix = "_averaged_q_network." if averaged else "q_network."
            weights = {k[len(prefix):]: torch.as_tensor(np.array(v)) for k, v in state.items()
                       if k.startswith(prefix)}
        except Exception as err:  # a damaged pickle raises any of several kinds
            raise PolicyError(f"checkpoint: {str(state_file)!r} is damaged or not a module state "
                              f"({type(err).__name__})") from None
        networks[module] = _with_weights(spec, weights, state_file)
    counters = _counters(checkpoint)
    policy = Policy(run.game, networks, specs, agent_modules, source=str(run_dir),
                    env_steps=_env_steps(run_dir, counters),
                    eval_settings={"episodes": run.eval.episodes, "seed": run.eval.seed})
    policy.training = _training(run_dir, policy.env_steps, counters, run.eval.seed)
    return policy


def _training(run_dir: Path, env_steps: int | None, counters: dict, seed: int) -> dict:
    """The card's ``training`` section for a run folder: its config.yaml whole, the checkpoint's counters,
    the training record (``training.json``), and result.json's evaluation where it is of this checkpoint."""
    import yaml

    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    record = _json_object(run_dir / TRAINING) or {}
    result = _json_object(run_dir / "result.json")
    evaluation = None
    if result is not None and isinstance(result.get("greedy"), dict) and result.get("env_steps") == env_steps:
        evaluation = {"env_steps": env_steps, "seed": result.get("seed", seed), "greedy": result["greedy"]}
    updates = counters.get("updates", record.get("learner_updates"))
    return {"config": config, "env_steps": env_steps, "learner_updates": None if updates is None else int(updates),
            **{key: record.get(key) for key in ("wall_seconds", "started", "ended", "hardware")},
            "commit": record.get("commit", "unknown"), "sessions": record.get("sessions", []),
            "evaluation": evaluation}


def _json_object(path: Path) -> dict | None:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _counters(checkpoint: Path) -> dict:
    """The counters the checkpoint saved ({} if it cannot be read)."""
    try:
        with (checkpoint / CHECKPOINT_STATE).open("rb") as f:
            return dict(pickle.load(f)["formation_counters"])
    except (OSError, pickle.UnpicklingError, EOFError, KeyError, TypeError, ValueError, AttributeError,
            ImportError):
        return {}


def _env_steps(run_dir: Path, counters: dict) -> int | None:
    """Env steps of the run's checkpoint (its saved counters); else result.json's, else the last
    metrics line's. result.json is written when a run ends, so after a resumed run was stopped it
    is older than the checkpoint."""
    try:
        return int(counters["env_steps"])
    except (KeyError, TypeError, ValueError):
        pass
    try:
        return int(json.loads((run_dir / "result.json").read_text())["env_steps"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        return int(json.loads(lines[-1])["env_steps"]) if lines else None
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None


# ---------------------------------------------------------------------- exports
def _load_export(folder: Path) -> Policy:
    card_file = folder / CARD
    try:
        card = json.loads(card_file.read_text())
    except (OSError, ValueError) as err:
        raise PolicyError(f"export: {str(card_file)!r} is not valid JSON ({type(err).__name__})") from None
    if not isinstance(card, dict):
        raise PolicyError(f"export: {str(card_file)!r} is not a policy card (a JSON object is needed)")
    version = card.get("format_version")
    if version != FORMAT_VERSION:
        raise PolicyError(f"export: {str(card_file)!r} has format_version {version!r}; "
                          f"this version reads {FORMAT_VERSION}")
    try:
        game = GameConfig.from_dict(card["game"])
    except ConfigError as err:
        raise PolicyError(f"export: {str(card_file)!r}: game.{err}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise PolicyError(f"export: {str(card_file)!r} is not a complete policy card "
                          f"({type(err).__name__}: {err})") from None
    try:
        specs = {m: NetworkSpec.from_dict(v, f"networks.{m}") for m, v in card["networks"].items()}
        agents_map = card["agents"]
        agent_modules = [agents_map[a] for a in game.agent_names]
        eval_settings = {k: int(card.get("eval", {}).get(k, DEFAULT_EVAL[k])) for k in DEFAULT_EVAL}
        env_steps = card.get("env_steps")
        env_steps = int(env_steps) if env_steps is not None else None
    except ConfigError as err:
        raise PolicyError(f"export: {str(card_file)!r}: {err}") from None
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise PolicyError(f"export: {str(card_file)!r} is not a complete policy card "
                          f"({type(err).__name__}: {err})") from None
    missing = sorted(set(agent_modules) - set(specs))
    if missing:
        raise PolicyError(f"export: {str(card_file)!r} maps agents to module(s) {missing} without a network")
    networks = {}
    for module in sorted(set(agent_modules)):
        weights_file = folder / f"{module}.pt"
        if not weights_file.is_file():
            raise PolicyError(f"export: {str(weights_file)!r} is missing (module {module!r} of {str(card_file)!r})")
        try:
            weights = torch.load(weights_file, map_location="cpu", weights_only=True)
        except Exception as err:  # truncated or foreign files raise any of several kinds
            raise PolicyError(f"export: {str(weights_file)!r} is damaged or not a state dict "
                              f"({type(err).__name__})") from None
        networks[module] = _with_weights(specs[module], weights, weights_file)
    policy = Policy(game, networks, {m: specs[m] for m in networks}, agent_modules, source=str(card.get("source")),
                    env_steps=env_steps, eval_settings=eval_settings)
    policy.refit_report = card.get("refit") if isinstance(card.get("refit"), dict) else None
    training = card.get("training")
    if not isinstance(training, dict | None):
        raise PolicyError(f"export: {str(card_file)!r} has a training section that is not a JSON object")
    policy.training = training
    threshold = card.get("veto_threshold", DEFAULT_VETO_THRESHOLD)
    if not (isinstance(threshold, int | float) and not isinstance(threshold, bool) and 0.0 <= threshold < 1.0):
        raise PolicyError(f"export: {str(card_file)!r} has veto_threshold {threshold!r}; allowed: a number in [0, 1)")
    policy.veto_threshold = float(threshold)
    fallback = card.get("veto_fallback", VETO_FALLBACKS[0])
    if fallback not in VETO_FALLBACKS:
        raise PolicyError(f"export: {str(card_file)!r} has veto_fallback {fallback!r}; allowed: "
                          f"{', '.join(VETO_FALLBACKS)}")
    policy.veto_fallback = fallback
    return policy


def how_trained(policy: Policy) -> dict | None:
    """What an evaluation report keeps of how ``policy`` was made (None for a card without a training section):
    the run's ``train.seed``, its env steps, the wall seconds of training and of every refit after it (None
    where none was), the hardware of training, and the options with which the planner took part (the run
    config's ``RunConfig.planner_options``, and ``refit.rounds`` after any refit; empty: from the reward alone;
    None where the card's run config does not load)."""
    training = policy.training
    if not training:
        return None
    refit, refit_seconds = policy.refit_report, None
    while isinstance(refit, dict) and isinstance(refit.get("seconds"), int | float):
        refit_seconds = (refit_seconds or 0.0) + refit["seconds"]
        refit = refit.get("earlier")
    train = (training.get("config") or {}).get("train") or {}
    planner_options = _planner_options(training.get("config"))
    if planner_options is not None and policy.refit_report and "refit.rounds" not in planner_options:
        planner_options.append("refit.rounds")  # a `formation refit` after training: the planner labelled it
    return {"seed": train.get("seed"), "env_steps": training.get("env_steps"),
            "wall_seconds": training.get("wall_seconds"), "refit_seconds": refit_seconds,
            "hardware": training.get("hardware"), "planner_options": planner_options}


def training_line(training: dict | None) -> str | None:
    """One line of how a policy was trained, e.g. ``trained: 200,064 env steps in 3.2 h on AMD EPYC 7B13
    (16 CPUs), NVIDIA H100 x1, 1 Ray node; commit 419508c``; None without a training section."""
    if not training:
        return None
    steps = training.get("env_steps")
    line = f"trained: {steps:,} env steps" if isinstance(steps, int) else "trained: unknown env steps"
    seconds, sessions = training.get("wall_seconds"), training.get("sessions") or [{}]
    if isinstance(seconds, int | float):
        # a run resumed from before training.json was written: its first recorded session did not start at 0
        partial = isinstance(sessions[0], dict) and bool((sessions[0].get("env_steps") or [0])[0])
        line += " in " + ("over " if partial else "") + (f"{seconds / 3600:.1f} h" if seconds >= 3600
                                                        else f"{seconds / 60:.1f} min")
    else:
        line += " in unrecorded time"
    line += f" on {_hardware_words(training.get('hardware'))}"
    commit = str(training.get("commit") or "unknown")
    sha, dirty, _ = commit.partition("-dirty")
    return line + f"; commit {sha[:12] if sha != 'unknown' else sha}{dirty}" + _teacher_words(training.get("config"))


def _planner_options(config: Any) -> list[str] | None:
    """``RunConfig.planner_options`` of a card's run config; None where it does not load."""
    try:
        return RunConfig.from_saved(config).planner_options
    except (ConfigError, TypeError, AttributeError):
        return None


def _teacher_words(config: Any) -> str:
    """What the training line says of the planner's part in training; nothing where the card's run config does
    not load."""
    used = _planner_options(config)
    if used is None:
        return ""
    return f"; the planner's labels ({', '.join(used)})" if used else "; from the reward alone, no planner"


def _hardware_words(hw: Any) -> str:
    if not isinstance(hw, dict):
        return "unrecorded hardware"
    words = [f"{hw.get('cpu') or 'unknown CPU'} ({hw.get('cpus')} CPUs)"]
    gpus = hw.get("gpus") or 0
    words.append(f"{hw.get('gpu')} x{gpus:g}" if hw.get("gpu") else "no GPU")
    nodes = hw.get("ray_nodes")
    if nodes:
        words.append(f"{nodes} Ray node{'s' if nodes != 1 else ''}")
    return ", ".join(words)


def _with_weights(spec: NetworkSpec, weights: Any, where: Path) -> DuelingQNetwork:
    if not isinstance(weights, dict):
        raise PolicyError(f"checkpoint: {str(where)!r} holds no state dict")
    try:
        net = spec.build()
    except (RuntimeError, ValueError, TypeError) as err:
        raise PolicyError(f"checkpoint: the network of {str(where)!r} cannot be built ({err})") from None
    try:
        net.load_state_dict(weights, strict=True)
    except (RuntimeError, TypeError, KeyError) as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        detail = (lines[1] if len(lines) > 1 else lines[0] if lines else type(err).__name__)[:200]
        raise PolicyError(f"checkpoint: {str(where)!r} does not fit the network its config describes ({detail})") \
            from None
    net.eval()
    return net


def within_veto(safe_probability: np.ndarray, threshold: float, fallback: str = VETO_FALLBACKS[0]) -> np.ndarray:
    """(N, 4, 4) bool: the joint moves whose safe probability (N, 4, 4) is above ``threshold``; in a state
    with none, by ``fallback``: ``above_half``, those above one half (and where none is, none:
    ``greedy_within`` then keeps to all); ``most_probable``, the joint moves of the highest probability."""
    if fallback not in VETO_FALLBACKS:
        raise ValueError(f"fallback: {fallback!r} is not allowed; allowed: {', '.join(VETO_FALLBACKS)}")
    strict = safe_probability > threshold
    if fallback == "most_probable":
        best = safe_probability >= safe_probability.max(axis=(1, 2), keepdims=True)
        return np.where(strict.any(axis=(1, 2), keepdims=True), strict, best)
    if threshold <= 0.5:
        return strict
    return np.where(strict.any(axis=(1, 2), keepdims=True), strict, safe_probability > 0.5)


def greedy_within(by_module: dict[str, np.ndarray], agent_modules: list[str], allowed: np.ndarray | None,
                  learned: np.ndarray | None) -> np.ndarray:
    """A leader's and a follower's greedy joint moves (N, 2) from their modules' Q-values ``by_module`` (a
    follower's that answers the leader: a row per leader move), within the joint moves (N, 4, 4) ``allowed``
    (a shield's; None: all) and, where they have some in common with it, those ``learned`` (a safety head's)."""
    leader_q, follower_q = by_module[agent_modules[0]], by_module[agent_modules[1]]
    if follower_q.shape[-1] == N_ACTIONS:  # it does not answer the leader: the same values for every move
        follower_q = np.repeat(follower_q[:, None], N_ACTIONS, axis=1)
    follower_q = follower_q.reshape(len(leader_q), N_ACTIONS, N_ACTIONS)
    if allowed is None:
        allowed = np.ones(follower_q.shape, bool)
    if learned is not None:  # within the shield's moves where they have some in common
        both = allowed & learned
        allowed = np.where(both.any(axis=(1, 2), keepdims=True), both, allowed)
    return shielded_moves(leader_q, follower_q, allowed)
