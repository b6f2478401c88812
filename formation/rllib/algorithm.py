"""FormationDQN: the paper's parallel double dueling DQN as an RLlib Algorithm.

Data path: rollout actors (``RolloutActor`` EnvRunners) play batches of games and push records to
the replay actor(s); the learner (``FormationLearner`` in RLlib's LearnerGroup) pulls batches
from the replay itself; the driver only starts work, keeps the replay ratio (learner updates
per env step), forwards weight references and reports metrics.

``build_algorithm_config(run)`` turns a ``RunConfig`` into the RLlib config: one RLModule per
policy (``leader``, ``follower`` or ``follower_i``) in a MultiRLModuleSpec, mapped from agents by
``policy_mapping_fn``. That config is the one source of truth: its RLlib fields that name a run-config key
(``RUN_FIELDS``, ``epsilon``) are that key, ``config.run`` is the run config with them merged in, and an RLlib option
the formation path does not honour is refused (``NOT_HONOURED``, EnvRunner callbacks: ``ENV_RUNNER_HOOKS``).
Results carry RLlib's standard keys (``env_runners``, ``evaluation``, ``learners``); docs/USAGE.md "Tune".
"""

from __future__ import annotations

import math
import pickle
import time
import weakref
from pathlib import Path
from typing import Any

import ray
import yaml
from ray.rllib.algorithms.dqn import DQN, DQNConfig
from ray.rllib.callbacks.utils import make_callback
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.from_config import NotProvided
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    EPISODE_AGENT_RETURN_MEAN,
    EPISODE_RETURN_MEAN,
    EVALUATION_RESULTS,
    LEARNER_RESULTS,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_EPISODES,
    NUM_EPISODES_LIFETIME,
    WEIGHTS_SEQ_NO,
)

from formation.config import ConfigError, RunFailed
from formation.evaluate import play_greedy
from formation.policy import CHECKPOINT_CONFIG
from formation.recipe.config import STOCK_TRAIN, RunConfig, TrainSettings
from formation.recipe.learn import loss_weights
from formation.recipe.replay import FrameReplay
from formation.recipe.stopwatch import Stopwatch, add_seconds
from formation.recipe.team import answers_leader, module_of_agent, network_specs, replay_frame_shape, spaces_of
from formation.rllib.learner import FormationLearner, team_weights
from formation.rllib.module import DuelingQModule
from formation.rllib.replay_actor import ReplayActor
from formation.rllib.rollout_actor import RolloutActor, no_episodes_yet


def policy_mapping_fn(agent_id, episode=None, **kwargs) -> str:
    """The leader has its own policy; the followers share one."""
    return "leader" if agent_id == "leader" else "follower"


# -- one source of truth: the RLlib fields that name a run-config key hold that key's value
# RLlib's field -> the run config's (section, key). The run config's other keys live in ``formation_run``; both
# paths honour these fields as RLlib documents them (the formation path counts target_network_update_freq in
# learner updates, as train.target_update_every does; the stock path in env steps, so it is not mapped there).
RUN_FIELDS: dict[str, tuple[str, str]] = {
    "lr": ("train", "lr"),
    "gamma": ("train", "gamma"),
    "n_step": ("train", "n_step"),
    "train_batch_size": ("train", "batch_size"),
    "target_network_update_freq": ("train", "target_update_every"),
    "grad_clip": ("train", "grad_clip"),
    "num_steps_sampled_before_learning_starts": ("train", "learning_starts"),
    "seed": ("train", "seed"),
    "num_env_runners": ("resources", "num_rollout_actors"),
    "num_envs_per_env_runner": ("resources", "games_per_actor"),
    "num_cpus_per_env_runner": ("resources", "cpus_per_rollout_actor"),
    "num_gpus_per_learner": ("resources", "num_gpus_per_learner"),
    "num_learners": ("resources", "num_learners"),
}
EPSILON_KEYS = ("epsilon_start", "epsilon_end", "epsilon_env_steps")  # RLlib's ``epsilon`` schedule

# RLlib options the formation path does not honour, and where their equivalent is set; a change is refused
NOT_HONOURED: dict[str, str] = {
    "double_q": "its target is always the double DQN target (formation.recipe.loss)",
    "dueling": "its networks are always dueling (train.hidden, train.channels)",
    "tau": "the target network is copied whole every train.target_update_every updates "
           "(target_network_update_freq)",
    "num_atoms": "its Q-values are not distributional",
    "v_min": "its Q-values are not distributional",
    "v_max": "its Q-values are not distributional",
    "noisy": "it explores epsilon-greedily: train.epsilon_start, epsilon_end, epsilon_env_steps, exploration",
    "sigma0": "it explores epsilon-greedily: train.epsilon_start, epsilon_end, epsilon_env_steps, exploration",
    "hiddens": "the networks are the run config's: train.hidden, train.channels, train.leader_window",
    "td_error_loss_fn": "its loss is formation.recipe.loss.dqn_loss (Huber TD error, plus the teacher's large "
                        "margin: teacher.margin, margin_gap)",
    "categorical_distribution_temperature": "its Q-values are not distributional",
    "adam_epsilon": "the learner's Adam keeps torch's default eps",
    "training_intensity": "learner updates per env step are train.replay_ratio",
    "replay_buffer_config": "its replay is an actor of its own: train.replay_capacity, train.prioritized, "
                            "resources.num_replay_shards",
    "store_buffer_in_checkpoints": "its replay is not checkpointed; a resumed run refills it",
    "before_learn_on_batch": "the learner pulls its batches from the replay itself",
    "burn_in_len": "its networks have no memory",
    "rollout_fragment_length": "a rollout actor plays train.steps_per_sample steps of its games per sample",
    "num_cpus_per_learner": "a CPU learner takes one CPU; resources.num_learners adds learners",
    "env": "the game is the run config's game section",
    "env_config": "the game is the run config's game section",
    "evaluation_interval": "greedy evaluation runs every eval.every_env_steps env steps on eval.episodes games, "
                           "reported under result['evaluation']",
    "evaluation_num_env_runners": "greedy evaluation runs in a Ray actor of its own beside training (eval.episodes)",
    "torch_compile_learner": "its learner runs torch eagerly",
    "optimizer": "its learner's Adam takes train.lr and clips to train.grad_clip",
    "_env_to_module_connector": "its rollout actors read the games' observations themselves, not through connectors",
    "_module_to_env_connector": "its rollout actors turn Q-values into moves themselves (formation.recipe.collect)",
    "_learner_connector": "its learner reads replay batches as formation.recipe.loss.module_batches splits them",
}
# EnvRunner hooks: the formation path's rollout actors play batched games, not RLlib episodes
ENV_RUNNER_HOOKS = ("on_environment_created", "on_episode_created", "on_episode_start", "on_episode_step",
                    "on_episode_end", "on_sample_end", "on_sub_environment_created", "on_postprocess_trajectory")


def _unresolved(value) -> bool:
    """A Tune search space (``tune.grid_search`` dict, ``tune.uniform`` domain): Tune resolves it per trial."""
    return isinstance(value, dict) or type(value).__module__.startswith("ray.tune")


def epsilon_keys(value) -> dict[str, Any]:
    """RLlib's ``epsilon`` (a number, or ``[(0, start), (env_steps, end)]``) as the run config's keys."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        return {"epsilon_start": value, "epsilon_end": value}
    points = list(value) if isinstance(value, list | tuple) else []
    if len(points) == 2 and all(isinstance(p, list | tuple) and len(p) == 2 for p in points) and points[0][0] == 0:
        (_, start), (steps, end) = points
        return {"epsilon_start": start, "epsilon_end": end, "epsilon_env_steps": steps}
    raise ConfigError(f"epsilon: {value!r} is not allowed on the formation path; allowed: a number, or "
                      "[(0, start), (env_steps, end)] (train.epsilon_start, epsilon_end, epsilon_env_steps)")


_FROZEN_RUNS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # config -> its run, once frozen


class RunConfigFields:
    """An RLlib config whose fields that name a run-config key (``run_fields``, and ``epsilon``) hold that key, and
    ``formation_run`` the run config's other keys: ``run`` merges them, so ``config.training(lr=...)``, a Tune search
    space and ``build_algorithm_config(run)`` all set one value, which rollout actors, learner, replay and evaluation
    read. An invalid value is the run config's one-line ``ConfigError``, when it is set."""

    run_fields = RUN_FIELDS

    @property
    def formation_run(self) -> dict:
        """The run config as a dict (``RunConfig.to_dict``) with the RLlib fields merged in (Tune's search spaces
        left out); not validated."""
        values = {k: dict(v) if isinstance(v, dict) else v for k, v in self._formation_run.items()}
        for attr, (section, key) in self.run_fields.items():
            if not _unresolved(getattr(self, attr)):
                values.setdefault(section, {})[key] = getattr(self, attr)
        if not _unresolved(self.epsilon):
            values.setdefault("train", {}).update(epsilon_keys(self.epsilon))
        return values

    @formation_run.setter
    def formation_run(self, values: dict) -> None:
        """The run config (a ``RunConfig.to_dict``): the keys RLlib names go to RLlib's fields, the rest here."""
        values = {k: dict(v) if isinstance(v, dict) else v for k, v in values.items()}
        fields = {}
        for attr, (section, key) in self.run_fields.items():
            if key in values.get(section, {}):
                fields[attr] = values[section].pop(key)
        train = values.get("train", {})
        if any(k in train for k in EPSILON_KEYS):
            t = RunConfig.from_dict({"train": {k: train.pop(k) for k in EPSILON_KEYS if k in train}}).train
            fields["epsilon"] = [(0, t.epsilon_start), (t.epsilon_env_steps, t.epsilon_end)]
        DQNConfig.__setattr__(self, "_formation_run", values)
        for attr, value in fields.items():
            DQNConfig.__setattr__(self, attr, value)
        self.run  # noqa: B018 (validates the whole)

    @property
    def run(self) -> RunConfig:
        """The run config, validated (once, for a frozen config: the algorithm's, learner's and rollout actors')."""
        if self._is_frozen and self in _FROZEN_RUNS:
            return _FROZEN_RUNS[self]
        for attr in (*self.run_fields, "epsilon"):
            if _unresolved(getattr(self, attr)):
                raise ConfigError(f"{attr}: {getattr(self, attr)!r} is a Tune search space; tune.Tuner resolves it")
        run = RunConfig.from_saved(self.formation_run)  # a checkpoint of an earlier version keeps what it trained with
        if self._is_frozen:
            _FROZEN_RUNS[self] = run
        return run

    def __setattr__(self, key, value):
        if key in (*self.run_fields, "epsilon") and "_formation_run" in self.__dict__ and not _unresolved(value):
            values = self.formation_run  # validate the new value as the run config's key
            if key == "epsilon":
                values["train"].update(epsilon_keys(value))
            else:
                section, name = self.run_fields[key]
                values[section][name] = value
            RunConfig.from_dict(values)
        super().__setattr__(key, value)


class FormationDQNConfig(RunConfigFields, DQNConfig):
    """The formation path's config. Its RLlib fields ``RUN_FIELDS`` and ``epsilon`` are the run config's keys (one
    value: ``run`` merges them in); a change to an option the path does not honour (``NOT_HONOURED``), or callbacks
    on EnvRunner hooks (``ENV_RUNNER_HOOKS``), is refused in one line."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or FormationDQN)
        # our replay lives in its own actor: no local buffer in the driver
        self.replay_buffer_config = {**self.replay_buffer_config, "no_local_replay_buffer": True}
        self.env_runners(env_runner_cls=RolloutActor, create_local_env_runner=False,
                         max_requests_in_flight_per_env_runner=2)
        self.formation_run = RunConfig().to_dict()

    def __setattr__(self, key, value):
        if "_formation_run" in self.__dict__ and not self.__dict__.get("in_evaluation"):
            if key in NOT_HONOURED and key in self.__dict__ and not _same(value, self.__dict__[key]):
                raise _not_honoured(key, value, repr(self.__dict__[key]))
            if key == "_train_batch_size_per_learner" and value is not None:  # RLlib's: the total over learners
                key, value = "train_batch_size", value * (self.num_learners or 1)
            _check_callbacks(key, value)
        super().__setattr__(key, value)

    def build_learner_group(self, *, placement_group=None, **kwargs):
        # the learners take the placement group FormationDQN.setup reserved for them (RLlib's own way of handing
        # a LearnerGroup its resources, as a Tune trial does)
        return super().build_learner_group(
            placement_group=placement_group or self.__dict__.get("_learners_placement"), **kwargs)

    def training(self, *, replay_buffer_config=NotProvided, **kwargs):
        # DQNConfig merges a replay_buffer_config into its own in place: compare before it does
        if replay_buffer_config is not NotProvided and "_formation_run" in self.__dict__ and any(
                not _same(value, self.replay_buffer_config.get(key)) for key, value in replay_buffer_config.items()):
            raise _not_honoured("replay_buffer_config", replay_buffer_config, "the default")
        return super().training(replay_buffer_config=replay_buffer_config, **kwargs)

    def get_default_learner_class(self):
        return FormationLearner

    # fields the learner reads through its config
    @property
    def loss_weights(self) -> dict[str, float]:
        return loss_weights(self.run)

    @property
    def prioritized(self) -> bool:
        return self.run.train.prioritized


def _not_honoured(key: str, value, allowed: str) -> ConfigError:
    name = key.lstrip("_")  # a connector's attribute is private; its setter's keyword is not
    return ConfigError(f"{name}={value!r}: the formation path does not honour it; {NOT_HONOURED[key]} "
                       f"(docs/CONFIG.md); allowed: {allowed}, or train.path: stock (RLlib's own DQN)")


def _same(a, b) -> bool:
    try:
        return bool(a == b)
    except Exception:  # e.g. arrays
        return a is b


def _check_callbacks(key: str, value) -> None:
    """Refuse, in one line, callbacks on EnvRunner hooks: they cannot fire on the formation path's rollout actors."""
    from ray.rllib.callbacks.callbacks import RLlibCallback

    hint = ("cannot fire on the formation path's rollout actors (they play batched games, not RLlib episodes); "
            "read result['env_runners'] and result['explore'] in on_train_result instead")
    if key.startswith("callbacks_on_") and key[len("callbacks_"):] in ENV_RUNNER_HOOKS and value is not None:
        raise ConfigError(f"callbacks({key[len('callbacks_'):]}=...): {hint}")
    if key == "callbacks_class" and value is not None:
        for cls in value if isinstance(value, list | tuple) else [value]:
            if not isinstance(cls, type):
                continue
            for hook in ENV_RUNNER_HOOKS:
                if getattr(cls, hook, None) is not getattr(RLlibCallback, hook, None):
                    raise ConfigError(f"callbacks: {cls.__name__}.{hook} {hint}")


def module_specs(run: RunConfig, inference_only: bool = False) -> dict[str, RLModuleSpec]:
    """One DuelingQModule spec per policy (its network: ``formation.recipe.team.network_specs``); every module acts in
    the env's actions, 0..3 (``DuelingQModule``). The exploration schedule is the config's ``epsilon``."""
    obs_space, act_space = spaces_of(run)
    return {m: RLModuleSpec(module_class=DuelingQModule, observation_space=obs_space, action_space=act_space,
                            model_config={"network": spec.to_dict(), "average_decay": run.train.average_decay},
                            inference_only=inference_only)
            for m, spec in network_specs(run).items()}


class StockFormationDQNConfig(RunConfigFields, DQNConfig):
    """RLlib's DQN on the RLlib view of the game; its fields that mean what the run config's keys mean are those
    keys (its target_network_update_freq counts env steps, the run config's learner updates: not one of them)."""

    run_fields = {k: v for k, v in RUN_FIELDS.items() if k not in ("target_network_update_freq", "num_learners")}

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or StockFormationDQN)
        self.formation_run = RunConfig(train=TrainSettings(path="stock", **STOCK_TRAIN)).to_dict()


def build_stock_config(run: RunConfig) -> StockFormationDQNConfig:
    """RLlib's DQN on the RLlib view of the game, with our modules and the same replay ratio."""
    from formation.rllib.env import register

    t, res = run.train, run.resources
    config = (
        StockFormationDQNConfig()
        .environment(register(), env_config=run.game.to_dict())
        .env_runners(rollout_fragment_length=t.steps_per_sample, create_local_env_runner=res.num_rollout_actors == 0)
        .learners(num_learners=0 if res.num_gpus_per_learner == 0 else 1)
        .multi_agent(policies=set(module_specs(run)), policy_mapping_fn=policy_mapping_fn)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs=module_specs(run)))
        .training(double_q=True, dueling=True, tau=1.0, grad_clip_by="global_norm",
                  target_network_update_freq=int(t.target_update_every / t.replay_ratio),
                  # RLlib samples once from every runner, then runs training_intensity / native ratio
                  # updates, where its native ratio counts one runner more than there are
                  training_intensity=t.replay_ratio * t.batch_size * max(res.num_rollout_actors, 1)
                  / (res.num_rollout_actors + 1),
                  replay_buffer_config={"type": "MultiAgentEpisodeReplayBuffer", "capacity": t.replay_capacity})
        .reporting(min_sample_timesteps_per_iteration=0, min_time_s_per_iteration=1.0)
    )
    config.formation_run = run.to_dict()  # lr, gamma, n_step, epsilon, ... and the actors: RUN_FIELDS
    return config


def build_algorithm_config(run: RunConfig):
    """The RLlib config of the run's path: ``formation`` (ours) or ``stock`` (RLlib's DQN)."""
    if run.train.path == "stock":
        return build_stock_config(run)
    return build_formation_config(run)


def build_formation_config(run: RunConfig) -> FormationDQNConfig:
    """The formation path's config: the run config (``formation_run``, which sets the RLlib fields it names:
    ``RUN_FIELDS``), one module per policy and its mapping."""
    specs = module_specs(run)
    config = (
        FormationDQNConfig()
        .multi_agent(policies=set(specs), policy_mapping_fn=policy_mapping_fn)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs=specs))
        .training(grad_clip_by="global_norm")
        .reporting(min_sample_timesteps_per_iteration=0, min_time_s_per_iteration=1.0)
        .fault_tolerance(restart_failed_env_runners=True, delay_between_env_runner_restarts_s=1.0)
        # the rollout actors have no connector states to merge: RLlib would otherwise ask every actor for its
        # state after every iteration, and wait for the slowest (it still sends them the env steps so far)
        .env_runners(merge_env_runner_states=False)
    )
    config.formation_run = run.to_dict()
    return config


def learner_values(results) -> list:
    """The values of a ``foreach_learner`` call; a learner that died stops the run in one line (RLlib
    does not restart learners, and its weights since the last checkpoint died with it)."""
    values = []
    for result in results:
        if not result.ok:
            error = result.get()
            first = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise RunFailed(f"the learner died ({type(error).__name__}: {first[:160]})")
        values.append(result.get())
    return values


def resource_bundles(run: RunConfig) -> list[dict[str, float]]:
    """What the run's actors ask Ray for: one bundle per rollout actor, and one per learner (a GPU learner asks
    for no CPU)."""
    res = run.resources
    learner = {"CPU": 1.0} if res.num_gpus_per_learner == 0 else {"GPU": float(res.num_gpus_per_learner)}
    return [{"CPU": float(res.cpus_per_rollout_actor)}] * res.num_rollout_actors + [learner] * res.num_learners


def missing_resources(run: RunConfig, have: dict[str, float]) -> str | None:
    """What the run asks for (``resource_bundles``) beyond ``have`` (Ray's cluster resources), as a one-line
    error; None if it fits."""
    res = run.resources
    asked = {kind: sum(b.get(kind, 0.0) for b in resource_bundles(run)) for kind in ("CPU", "GPU")}
    if asked["GPU"] > have.get("GPU", 0):
        by, then = ("", "the learner then runs") if res.num_learners == 1 else \
            (f" by {res.num_learners} learners", "the learners then run")
        return (f"resources.num_gpus_per_learner: {asked['GPU']:g} GPU asked{by}, the Ray cluster has "
                f"{have.get('GPU', 0):g}; allowed here: 0 ({then} on CPU)")
    if asked["CPU"] > have.get("CPU", 0):
        learners = "the learner" if res.num_learners == 1 else f"{res.num_learners} learners"
        return (f"resources.num_rollout_actors: {res.num_rollout_actors} actors x {res.cpus_per_rollout_actor:g} CPU "
                f"+ {learners} need {asked['CPU']:g} CPUs, the Ray cluster has {have.get('CPU', 0):g}; "
                "lower num_rollout_actors, cpus_per_rollout_actor or num_learners")
    return None


def reserve_learners(run: RunConfig, timeout_s: float = 60.0):
    """A placement group of the learners' bundles, ready before any rollout actor is placed: rollout actors of a
    fraction of a CPU, placed first, can leave every node short of the whole CPU a learner asks for (the run
    would wait for ever). None inside a placement group already (a Tune trial's holds the learners)."""
    from ray.util.placement_group import get_current_placement_group, placement_group, remove_placement_group

    if get_current_placement_group() is not None or run.resources.num_learners == 0:
        return None
    bundles = resource_bundles(run)[run.resources.num_rollout_actors:]
    reserved = placement_group(bundles, strategy="PACK")
    ready, _ = ray.wait([reserved.ready()], timeout=timeout_s)
    if not ready:
        remove_placement_group(reserved)
        raise RunFailed(f"resources.num_learners: {run.resources.num_learners} learner(s) of {bundles[0]} each "
                        f"could not be placed in {timeout_s:g} s; free: {ray.available_resources()}")
    return reserved


def replay_shard(run: RunConfig) -> dict:
    """One replay shard's arguments (capacity, frame shape, agents, frame stack) and Ray options: it asks for
    the memory its arrays take, so that Ray places it on a node that can hold it, and the shards spread over
    the cluster's nodes rather than all landing on the head."""
    args = (max(1, run.train.replay_capacity // run.resources.num_replay_shards), replay_frame_shape(run),
            1 + run.game.n_followers, run.game.frame_stack)
    memory = FrameReplay(*args, prioritized=run.train.prioritized).nbytes  # numpy's zeros: nothing touched yet
    return {"args": args, "options": {"memory": memory, "scheduling_strategy": "SPREAD"}}


def modules_of(run: RunConfig, weights: dict) -> dict:
    """The run's modules (inference parts) with ``weights``, on the CPU."""
    multi = MultiRLModuleSpec(rl_module_specs=module_specs(run, inference_only=True)).build()
    multi.set_state(weights)
    return {m: multi[m] for m in multi.keys()}


def team_of(run: RunConfig, modules: dict, source: str = "training", env_steps: int | None = None):
    """The greedy team of ``modules`` as ``formation.policy.load`` restores it (with its safety heads' veto, if any)."""
    from formation.policy import Policy

    specs = network_specs(run)
    return Policy(run.game, {m: modules[m].q_network for m in specs}, specs, module_of_agent(run), source=source,
                  env_steps=env_steps, eval_settings={"episodes": run.eval.episodes, "seed": run.eval.seed})


def play_team(run: RunConfig, modules: dict, episodes: int, seed: int, record: int = 0) -> dict:
    """``formation.evaluate.play_greedy`` of the team as ``formation.policy.load`` restores it."""
    return play_greedy(run.game, team_of(run, modules).act_batch, episodes, seed, record=record)


# short and periodic: it shares the cores rather than waiting for one of its own; restarted if it dies (the
# evaluation it played is then lost, and the next one is due at once)
@ray.remote(num_cpus=0, max_restarts=-1)
class EvaluationActor:
    """The periodic greedy evaluation, in a process of its own beside training, started with the run so that an
    evaluation never waits for a process to start."""

    def __init__(self, run: dict):
        import torch

        torch.set_num_threads(1)
        self.run = RunConfig.from_saved(run)

    def evaluate(self, weights: dict, episodes: int, seed: int) -> dict:
        return play_team(self.run, modules_of(self.run, weights), episodes, seed)["summary"]


class GreedyEvaluationMixin:
    """What both paths share: counters, greedy evaluation, and their place in checkpoints."""

    # -- greedy evaluation (the same code as `formation evaluate`)
    def evaluate_greedy(self, episodes: int | None = None, seed: int | None = None) -> dict:
        """Summary rates of greedy play on held-out scenarios (``formation.evaluate.play_greedy``)."""
        return self.play_greedy(episodes, seed)["summary"]

    def _evaluate_now(self) -> None:
        """Start the periodic greedy evaluation (``eval.every_env_steps``) on the weights of now, in an actor of its
        own (``EvaluationActor``), after RLlib's ``on_evaluate_start`` callbacks; training goes on meanwhile.
        ``_collect_evaluation`` takes its summary in."""
        make_callback("on_evaluate_start", callbacks_objects=self.callbacks,
                      callbacks_functions=self.config.callbacks_on_evaluate_start,
                      kwargs=dict(algorithm=self, metrics_logger=self.metrics))
        weights = self._inference_weights()
        self._evaluation = (self.counters["env_steps"], weights,
                            self._evaluator.evaluate.remote(weights, self.run.eval.episodes, self.run.eval.seed))

    def _evaluation_due(self) -> bool:
        """Whether to start the next evaluation: its env steps reached, and the last one back."""
        return self._evaluation is None and self.counters["env_steps"] >= self.counters["next_eval_at"]

    def _collect_evaluation(self) -> None:
        """The evaluation in flight, once it is back: ``last_eval`` keeps its summary and the env steps of the
        weights it played (``result["evaluation"]`` reports both), ``last_eval_weights`` those weights (for
        ``formation train`` to keep the best team), then RLlib's ``on_evaluate_end`` callbacks."""
        if self._evaluation is None:
            return
        env_steps, weights, ref = self._evaluation
        if not ray.wait([ref], timeout=0)[0]:
            return
        self._evaluation = None
        try:
            self.last_eval = {**ray.get(ref), "env_steps": env_steps}
        except ray.exceptions.RayActorError:  # it died playing: Ray restarts it for the next one
            return
        self.last_eval_weights = weights
        make_callback("on_evaluate_end", callbacks_objects=self.callbacks,
                      callbacks_functions=self.config.callbacks_on_evaluate_end,
                      kwargs=dict(algorithm=self, metrics_logger=self.metrics,
                                  evaluation_metrics=evaluation_results(self.last_eval, self.run)))

    def cleanup(self) -> None:
        super().cleanup()
        ray.kill(self._evaluator)
        if getattr(self, "_learners_placement", None) is not None:
            ray.util.remove_placement_group(self._learners_placement)

    def _evaluate_when_due(self) -> None:
        self._collect_evaluation()
        if self._evaluation_due():
            self._evaluate_now()
            self.counters["next_eval_at"] += self.run.eval.every_env_steps

    def _log_evaluation(self) -> None:
        """``result["evaluation"]``: the last greedy evaluation, NaN before the first."""
        for key, value in flatten_numbers(evaluation_results(self.last_eval, self.run)).items():
            self.metrics.log_value((EVALUATION_RESULTS, *key), value, window=1)

    def play_greedy(self, episodes: int | None = None, seed: int | None = None, record: int = 0) -> dict:
        run = self.run
        return play_team(run, self.local_modules(), episodes or run.eval.episodes,
                         run.eval.seed if seed is None else seed, record)

    def _inference_weights(self) -> dict:
        """The weights of the team as it is now, inference parts only: the learner's moving average where the run
        keeps one (``train.average_decay``), else its modules' (the learners hold equal weights)."""
        return learner_values(self.learner_group.foreach_learner(team_weights))[0]

    def local_modules(self) -> dict:
        """CPU copies of the learner's current modules."""
        return modules_of(self.run, self._inference_weights())

    # -- checkpoints: our counters ride along in algorithm_state.pkl, the run config beside it
    def save_to_path(self, path=None, *, filesystem=None, **kwargs) -> str:
        """RLlib's checkpoint, and the run config as ``config.yaml`` in it, so that ``formation.policy.load`` and
        ``formation export`` read a checkpoint on its own (a Tune trial's) without Ray."""
        path = super().save_to_path(path, filesystem=filesystem, **kwargs)
        if filesystem is None:  # a local folder (formation train uploads its own copies)
            Path(path, CHECKPOINT_CONFIG).write_text(yaml.safe_dump(self.run.to_dict(), sort_keys=False))
        return path

    def get_state(self, *args, **kwargs):
        state = super().get_state(*args, **kwargs)
        state["formation_counters"] = dict(self.counters)
        state["formation_last_eval"] = dict(self.last_eval)
        return state

    def replay_stats(self) -> list[dict]:
        return ray.get([r.stats.remote() for r in self.replays])

    def set_state(self, state, *args, **kwargs):
        super().set_state(state, *args, **kwargs)
        if "formation_counters" in state:
            self.counters.update(state["formation_counters"])
            self.last_eval = dict(state.get("formation_last_eval", {}))
            self._after_restore()


    def _after_restore(self) -> None:
        pass


class FormationDQN(GreedyEvaluationMixin, DQN):
    @classmethod
    def get_default_config(cls) -> FormationDQNConfig:
        return FormationDQNConfig()

    @classmethod
    def from_checkpoint(cls, path, filesystem=None, *, resources: dict | None = None, **kwargs):
        """RLlib's ``Algorithm.from_checkpoint``, with ``resources``: keys of the run config's ``resources`` section
        that replace the saved run's, so that a run saved on a cluster restores on a laptop. A run that asks for
        more than the Ray it restores into has is refused in one line (``missing_resources``), instead of waiting
        for ever."""
        if "config" not in kwargs:
            with open(Path(path) / cls.CLASS_AND_CTOR_ARGS_FILE_NAME, "rb") as f:
                state = pickle.load(f)["ctor_args_and_kwargs"][0][0]  # the saved config's get_state()
            config = FormationDQNConfig().update_from_dict(state)
            values = config.formation_run
            values["resources"] = {**values.get("resources", {}), **(resources or {})}
            config.formation_run = values  # a bad key or value: the run config's one-line error
            kwargs["config"] = config
        if not ray.is_initialized():
            ray.init()  # as building the algorithm would
        missing = missing_resources(kwargs["config"].run, ray.cluster_resources())
        if missing is not None:
            raise ConfigError(missing)
        return super().from_checkpoint(path, filesystem, **kwargs)

    def setup(self, config: FormationDQNConfig) -> None:
        self._learners_placement = reserve_learners(config.run)
        # the config is frozen by now: its __dict__ is the one place RLlib's setup passes on to build_learner_group
        self.config.__dict__["_learners_placement"] = self._learners_placement
        super().setup(config)
        run = self.run = config.run
        shard = replay_shard(run)
        self.replays = [ReplayActor.options(**shard["options"]).remote(*shard["args"], seed=run.train.seed + i,
                                                                       prioritized=run.train.prioritized)
                        for i in range(run.resources.num_replay_shards)]
        # driver_bytes: pickled size of all that rollout actors and the learner returned to the driver (each
        # measures its own answers, off the driver)
        # updates_skipped: what the replay ratio owed while a restarted replay refilled (never run)
        # samples_lost: sample requests that died with their rollout actor (each up to steps_per_sample x
        # games_per_actor env steps, never counted in env_steps)
        self.counters = {"env_steps": 0, "updates": 0, "episodes": 0, "weights_pushed_at": 0, "driver_bytes": 0,
                         "next_eval_at": run.eval.every_env_steps, "updates_skipped": 0,
                         "rollout_actor_restarts": 0, "replay_restarts": 0, "samples_lost": 0}
        self._samples = {"sent": 0, "answered": 0}  # sample requests of this process's life
        self.last_eval: dict = {}
        self._no_episodes_yet = no_episodes_yet(run, self.config.metrics_num_episodes_for_smoothing)
        self._evaluation = None  # (env steps of its weights, the weights, its answer) while one plays
        self.last_eval_weights: dict | None = None
        self._evaluator = EvaluationActor.remote(run.to_dict())  # ready before the first evaluation is due
        self._replay_ready = False
        self._incarnations: dict[int, str] = {}  # of each replay shard, as the learner last saw it
        self._started = time.perf_counter()
        self.clock = Stopwatch()  # the driver's seconds per stage; the other processes' come with their results
        self.account: dict[str, dict[str, float]] = {"rollout": {}, "learner": {}}
        self._share_replays()
        agents = module_of_agent(run)
        answering = [m for m in set(agents) if answers_leader(run, m)]
        replays, safety = self.replays, run.safety_head
        self.learner_group.foreach_learner(lambda learner: learner.set_replays(replays, agents, answering, safety))

    def _after_restore(self) -> None:
        self._log_lifetime()
        self._push_weights()

    # -- wiring
    def _share_replays(self, runner_ids=None) -> None:
        """Each rollout actor's replay shard (``runner_ids``: these only). The learners are wired once, in setup: a
        restarted rollout actor leaves their batches and prefetches as they are."""
        replays = self.replays
        n = len(replays)
        self.env_runner_group.foreach_env_runner(
            lambda runner: runner.set_replay(replays[(getattr(runner, "worker_index", 0) or 0) % n]),
            remote_worker_ids=runner_ids, local_env_runner=False)

    def restore_env_runners(self, env_runner_group):
        restored = super().restore_env_runners(env_runner_group)
        if restored:  # a restarted actor is a fresh process: hand it the replay and the weights again
            self.counters["rollout_actor_restarts"] += len(restored)
            self._share_replays(restored)
            self._push_weights(restored)
        return restored

    def _push_weights(self, runner_ids=None) -> None:
        (ref, seq), *_ = learner_values(self.learner_group.foreach_learner(lambda learner: learner.weights_ref()))
        state = {COMPONENT_RL_MODULE: ref, WEIGHTS_SEQ_NO: seq,
                 NUM_ENV_STEPS_SAMPLED_LIFETIME: self.counters["env_steps"]}
        self.env_runner_group.foreach_env_runner("set_state", kwargs={"state": state}, remote_worker_ids=runner_ids,
                                                 local_env_runner=False, timeout_seconds=0.0)

    # -- one training step
    def training_step(self) -> None:
        t, c = self.run.train, self.counters
        steps_per_request = t.steps_per_sample * self.run.resources.games_per_actor
        updates_per_call = max(1, min(64, int(round(t.replay_ratio * steps_per_request))))
        learning = self._learning_ready()
        if not learning and c["updates"] > 0:
            # a replay restarted empty: the updates owed while it refills are skipped, not run later on
            # a replay of a few records
            c["updates_skipped"] = max(c["updates_skipped"], int(t.replay_ratio * c["env_steps"]) - c["updates"])
        # Sampling runs ahead of the learner by at most one call of updates plus one request per
        # actor, counting the steps of requests still in flight, so the ratio holds at any load;
        # and by that much, so that every actor has its next request while the learner updates on
        # the steps of its last (sampling and learning overlap instead of taking turns).
        actors = max(1, self.env_runner_group.num_healthy_remote_workers())
        in_flight = self.env_runner_group.num_in_flight_async_reqs(tag="sample") * steps_per_request
        owed_ahead = t.replay_ratio * (c["env_steps"] + in_flight) - c["updates"] - c["updates_skipped"]
        lead = updates_per_call + t.replay_ratio * steps_per_request * actors
        clock, account = self.clock, self.account
        if not learning or owed_ahead < lead:
            with clock("request"):
                self._samples["sent"] += self.env_runner_group.foreach_env_runner_async("sample", tag="sample")
        with clock("fetch"):  # mostly waiting: up to 10 ms for a rollout actor's answer
            ready = self.env_runner_group.fetch_ready_async_reqs(tags="sample", timeout_seconds=0.01)
        self._samples["answered"] += len(ready)
        self._count_lost_samples()
        for _, result in ready:
            c["env_steps"] += result["env_steps"]
            c["episodes"] += result["episodes"]
            c["driver_bytes"] += result["bytes"]
            add_seconds(account["rollout"], result.get("seconds", {}))
        # the actors' episode metrics, reduced in each actor: merged as RLlib merges its EnvRunners'; before the
        # first episode ends, RLlib's env_runners keys all the same (counts of 0, means NaN)
        records = [result["metrics"] for _, result in ready]
        self.metrics.aggregate(records if c["episodes"] else [*records, self._no_episodes_yet])
        owed = t.replay_ratio * c["env_steps"] - c["updates"] - c["updates_skipped"]
        if learning and owed >= 1:
            n, need = int(min(owed, updates_per_call)), self._min_records()
            with clock("learner"):  # waiting for the learner's updates
                results = learner_values(self.learner_group.foreach_learner(
                    lambda learner, n=n, need=need: learner.pull_and_update(n, need)))
            c["driver_bytes"] += sum(r["bytes"] for r in results)
            self.metrics.aggregate([r["metrics"] for r in results], key=LEARNER_RESULTS)
            c["updates"] += n  # every learner ran n updates of the same weights, on its own shards' batches
            for r in results:
                add_seconds(account["learner"], r.get("seconds", {}))
                self._note_incarnations(r["incarnations"])
                if r["refilling"]:  # a replay restarted and holds too few records: wait for the refill
                    self._replay_ready = False
            if c["updates"] - c["weights_pushed_at"] >= t.weights_every_updates:
                with clock("sync"):
                    self._push_weights()
                c["weights_pushed_at"] = c["updates"]
        elif not learning:
            with clock("fetch"):
                time.sleep(0.01)
        with clock("evaluation"):  # starting one, or taking one in: it plays in a task of its own
            self._evaluate_when_due()
        self._log_counters()

    def _count_lost_samples(self) -> None:
        """Requests neither answered nor in flight died with their actor (RLlib drops a failed actor's requests)."""
        s = self._samples
        lost = s["sent"] - s["answered"] - self.env_runner_group.num_in_flight_async_reqs(tag="sample")
        if lost > 0:
            self.counters["samples_lost"] += lost
            s["answered"] += lost

    def time_account(self) -> dict[str, dict[str, float]]:
        """Seconds in each stage of each kind of process since the last call, summed over the processes
        of that kind (``formation.recipe.stopwatch``): the ``driver``, the ``rollout`` actors, the
        ``learner`` and the ``replay`` shards."""
        replay: dict[str, float] = {}
        for seconds in ray.get([r.seconds.remote() for r in self.replays]):
            add_seconds(replay, seconds)
        out = {**self.account, "driver": self.clock.pop(), "replay": replay}
        self.account = {"rollout": {}, "learner": {}}
        return out

    def _min_records(self) -> int:
        return max(self.run.train.learning_starts, self.run.train.batch_size)

    def _learning_ready(self) -> bool:
        if not self._replay_ready:
            self._replay_ready = all(ray.get([r.ready.remote(self._min_records()) for r in self.replays]))
        return self._replay_ready

    def _note_incarnations(self, seen: dict[int, str]) -> None:
        """Count replay restarts; after one, learning waits until that replay is refilled."""
        for index, incarnation in seen.items():
            before = self._incarnations.get(index)
            if before is not None and before != incarnation:
                self.counters["replay_restarts"] += 1
            self._incarnations[index] = incarnation

    def _log_counters(self) -> None:
        c = self.counters
        elapsed = time.perf_counter() - self._started
        m = self.metrics
        m.log_value("env_steps", c["env_steps"], window=1)
        m.log_value("learner_updates", c["updates"], window=1)
        m.log_value("episodes", c["episodes"], window=1)
        m.log_value(NUM_ENV_STEPS_SAMPLED_LIFETIME, c["env_steps"], window=1)
        m.log_value("session_seconds", elapsed, window=1)
        self._log_lifetime()
        self._log_evaluation()

    def _log_lifetime(self) -> None:
        """RLlib's lifetime counters (lifetime sums, kept in checkpoints) brought up to ours. RLlib reads
        ``env_runners/num_env_steps_sampled_lifetime`` to tell every rollout actor the env steps so far (its epsilon
        schedule's clock) after each iteration and restore."""
        for key, count in ((NUM_ENV_STEPS_SAMPLED_LIFETIME, "env_steps"), (NUM_EPISODES_LIFETIME, "episodes")):
            behind = self.counters[count] - self.metrics.peek((ENV_RUNNER_RESULTS, key), default=0)
            self.metrics.log_value((ENV_RUNNER_RESULTS, key), max(behind, 0), reduce="lifetime_sum")


class StockFormationDQN(GreedyEvaluationMixin, DQN):
    """RLlib's own DQN training step (its EnvRunners, episode replay buffer and DQN loss) on the
    same game, modules and replay ratio: the reference the data path is measured against."""

    def setup(self, config) -> None:
        super().setup(config)
        self.run = config.run
        self.counters = {"env_steps": 0, "updates": 0, "episodes": 0, "driver_bytes": 0,
                         "next_eval_at": self.run.eval.every_env_steps}
        self.last_eval: dict = {}
        self._evaluation, self._evaluator = None, EvaluationActor.remote(self.run.to_dict())
        self.last_eval_weights: dict | None = None
        self._started = time.perf_counter()
        update = self.learner_group.update

        def counted_update(*args, **kwargs):
            self.counters["updates"] += 1
            return update(*args, **kwargs)

        self.learner_group.update = counted_update

    def training_step(self) -> None:
        super().training_step()
        c = self.counters
        c["env_steps"] = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        c["episodes"] = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_EPISODES_LIFETIME), default=0))
        self._evaluate_when_due()
        self._log_evaluation()


# the greedy evaluation's rates (formation.evaluate.play_greedy's summary) under result["evaluation"], and the env
# steps of the weights it played
EVALUATION_RATES = ("success", "leader_collision", "follower_collision", "formation_broken", "timeout",
                    "steps_success_mean", "env_steps")


def evaluation_results(summary: dict, run: RunConfig) -> dict:
    """``result["evaluation"]`` of a greedy evaluation's summary (``{}``: none yet, every value NaN): its rates, and
    RLlib's ``env_runners`` keys (the team's return, summed over agents as RLlib's multi-agent episodes count it)."""
    returns = summary.get("return_mean") or {name: math.nan for name in run.game.agent_names}
    rates = {key: math.nan if summary.get(key) is None else float(summary[key]) for key in EVALUATION_RATES}
    return {**rates, ENV_RUNNER_RESULTS: {
        EPISODE_RETURN_MEAN: float(sum(returns.values())),
        EPISODE_AGENT_RETURN_MEAN: {name: float(v) for name, v in returns.items()},
        NUM_EPISODES: float(summary.get("episodes", math.nan))}}


def flatten_numbers(values: dict, prefix: tuple = ()) -> dict[tuple, float]:
    out = {}
    for key, value in values.items():
        if isinstance(value, dict):
            out.update(flatten_numbers(value, (*prefix, key)))
        else:
            out[(*prefix, key)] = value
    return out
