"""FormationDQN: the paper's parallel double dueling DQN as an RLlib Algorithm.

Data path: rollout actors (``RolloutActor`` EnvRunners) play batches of games and push records to
the replay actor(s); the learner (``FormationLearner`` in RLlib's LearnerGroup) pulls batches
from the replay itself; the driver only starts work, keeps the replay ratio (learner updates
per env step), forwards weight references and reports metrics.

``build_algorithm_config(run)`` turns a ``RunConfig`` into the RLlib config: one RLModule per
policy (``leader``, ``follower`` or ``follower_i``) in a MultiRLModuleSpec, mapped from agents by
``policy_mapping_fn``.
"""

from __future__ import annotations

import pickle
import time

import gymnasium as gym
import ray
from ray.rllib.algorithms.dqn import DQN, DQNConfig
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    LEARNER_RESULTS,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_EPISODES_LIFETIME,
    WEIGHTS_SEQ_NO,
)

from formation.config import RunFailed
from formation.evaluate import play_greedy
from formation.recipe.config import RunConfig
from formation.recipe.rollout import STARTS
from formation.recipe.team import answers_leader, module_of_agent, network_specs, spaces_of
from formation.rllib.learner import FormationLearner
from formation.rllib.module import DuelingQModule
from formation.rllib.replay_actor import ReplayActor
from formation.rllib.rollout_actor import RolloutActor


def policy_mapping_fn(agent_id, episode=None, **kwargs) -> str:
    """Agents to policies when every agent has its own (``followers_share_policy: false``)."""
    return agent_id


def shared_follower_mapping_fn(agent_id, episode=None, **kwargs) -> str:
    return "leader" if agent_id == "leader" else "follower"


class FormationDQNConfig(DQNConfig):
    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or FormationDQN)
        self.formation_run: dict = RunConfig().to_dict()
        # our replay lives in its own actor: no local buffer in the driver
        self.replay_buffer_config = {**self.replay_buffer_config, "no_local_replay_buffer": True}

    def get_default_learner_class(self):
        return FormationLearner

    @property
    def run(self) -> RunConfig:
        return RunConfig.from_dict(self.formation_run)

    # fields the learner reads through its config
    @property
    def n_step(self) -> int:
        return self.run.train.n_step

    @n_step.setter
    def n_step(self, value) -> None:  # DQNConfig sets a default at construction
        pass

    @property
    def margin(self) -> float:
        return self.run.train.margin

    @property
    def margin_gap(self) -> float:
        return self.run.train.margin_gap

    @property
    def safety_weight(self) -> float:
        return self.run.train.safety_weight

    @property
    def prioritized(self) -> bool:
        return self.run.train.prioritized


def module_specs(run: RunConfig, inference_only: bool = False) -> dict[str, RLModuleSpec]:
    """One DuelingQModule spec per policy: its network (``formation.recipe.team.network_specs``) and the
    exploration schedule."""
    t = run.train
    obs_space, act_space = spaces_of(run)
    epsilon = [(0, t.epsilon_start), (t.epsilon_env_steps, t.epsilon_end)]
    return {m: RLModuleSpec(module_class=DuelingQModule, observation_space=obs_space,
                            action_space=gym.spaces.Discrete(16) if spec.answers_leader else act_space,
                            model_config={"network": spec.to_dict(), "epsilon": epsilon},
                            inference_only=inference_only)
            for m, spec in network_specs(run).items()}


class StockFormationDQNConfig(DQNConfig):
    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or StockFormationDQN)
        self.formation_run: dict = RunConfig().to_dict()

    @property
    def run(self) -> RunConfig:
        return RunConfig.from_dict(self.formation_run)


def build_stock_config(run: RunConfig) -> StockFormationDQNConfig:
    """RLlib's DQN on the RLlib view of the game, with our modules and the same replay ratio."""
    from formation.env.rllib import register

    t, res = run.train, run.resources
    mapping = shared_follower_mapping_fn if t.followers_share_policy else policy_mapping_fn
    fragment = t.steps_per_sample
    config = (
        StockFormationDQNConfig()
        .environment(register(), env_config=run.game.to_dict())
        .env_runners(num_env_runners=res.num_rollout_actors, num_cpus_per_env_runner=res.cpus_per_rollout_actor,
                     num_envs_per_env_runner=res.games_per_actor, rollout_fragment_length=fragment,
                     create_local_env_runner=res.num_rollout_actors == 0)
        .learners(num_learners=0 if res.num_gpus_per_learner == 0 else 1, num_gpus_per_learner=res.num_gpus_per_learner)
        .multi_agent(policies=set(module_specs(run)), policy_mapping_fn=mapping)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs=module_specs(run)))
        .training(lr=t.lr, gamma=t.gamma, train_batch_size=t.batch_size,
                  n_step=t.n_step, double_q=True, dueling=True,
                  target_network_update_freq=int(t.target_update_every / t.replay_ratio), tau=1.0,
                  grad_clip=t.grad_clip, grad_clip_by="global_norm",
                  num_steps_sampled_before_learning_starts=t.learning_starts,
                  # RLlib samples once from every runner, then runs training_intensity / native ratio
                  # updates, where its native ratio counts one runner more than there are
                  training_intensity=t.replay_ratio * t.batch_size * max(res.num_rollout_actors, 1)
                  / (res.num_rollout_actors + 1),
                  epsilon=[(0, t.epsilon_start), (t.epsilon_env_steps, t.epsilon_end)],
                  replay_buffer_config={"type": "MultiAgentEpisodeReplayBuffer", "capacity": t.replay_capacity})
        .reporting(min_sample_timesteps_per_iteration=0, min_time_s_per_iteration=1.0)
        .debugging(seed=t.seed)
    )
    config.formation_run = run.to_dict()
    return config


def build_algorithm_config(run: RunConfig):
    """The RLlib config of the run's path: ``formation`` (ours) or ``stock`` (RLlib's DQN)."""
    if run.train.path == "stock":
        return build_stock_config(run)
    return build_formation_config(run)


def build_formation_config(run: RunConfig) -> FormationDQNConfig:
    t, res = run.train, run.resources
    specs = module_specs(run)
    modules = sorted(specs)
    mapping = shared_follower_mapping_fn if t.followers_share_policy else policy_mapping_fn
    config = (
        FormationDQNConfig()
        .environment(env=None, env_config={})
        .env_runners(env_runner_cls=RolloutActor, num_env_runners=res.num_rollout_actors,
                     num_cpus_per_env_runner=res.cpus_per_rollout_actor, create_local_env_runner=False,
                     max_requests_in_flight_per_env_runner=2)
        .learners(num_learners=1, num_gpus_per_learner=res.num_gpus_per_learner,
                  num_cpus_per_learner=1 if res.num_gpus_per_learner == 0 else 0)
        .multi_agent(policies=set(modules), policy_mapping_fn=mapping)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs=specs))
        .training(lr=t.lr, gamma=t.gamma, train_batch_size=t.batch_size,
                  target_network_update_freq=t.target_update_every, tau=1.0, grad_clip=t.grad_clip,
                  grad_clip_by="global_norm")
        .reporting(min_sample_timesteps_per_iteration=0, min_time_s_per_iteration=1.0)
        .fault_tolerance(restart_failed_env_runners=True, delay_between_env_runner_restarts_s=1.0)
        .debugging(seed=t.seed)
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


class GreedyEvaluationMixin:
    """What both paths share: counters, greedy evaluation, and their place in checkpoints."""

    # -- greedy evaluation (the same code as `formation evaluate`)
    def evaluate_greedy(self, episodes: int | None = None, seed: int | None = None) -> dict:
        """Summary rates of greedy play on held-out scenarios (``formation.evaluate.play_greedy``)."""
        return self.play_greedy(episodes, seed)["summary"]

    def play_greedy(self, episodes: int | None = None, seed: int | None = None, record: int = 0) -> dict:
        from formation.policy import Policy

        run = self.run
        modules = self.local_modules()
        specs = network_specs(run)
        # the team as formation.policy.load restores it (with its safety heads' veto, if any)
        team = Policy(run.game, {m: modules[m].q_network for m in specs}, specs, module_of_agent(run),
                      source="training")
        return play_greedy(run.game, team.act_batch, episodes or run.eval.episodes,
                           run.eval.seed if seed is None else seed, record=record)

    def local_modules(self) -> dict:
        """CPU copies of the learner's current modules."""
        weights, = learner_values(self.learner_group.foreach_learner(
            lambda learner: learner.get_state(components=COMPONENT_RL_MODULE, inference_only=True)
            [COMPONENT_RL_MODULE]))
        multi = MultiRLModuleSpec(rl_module_specs=module_specs(self.run, inference_only=True)).build()
        multi.set_state(weights)
        return {m: multi[m] for m in multi.keys()}

    # -- checkpoints: our counters ride along in algorithm_state.pkl
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

    def setup(self, config: FormationDQNConfig) -> None:
        super().setup(config)
        run = self.run = config.run
        frame_shape = _frame_shape(run)
        self.replays = [ReplayActor.remote(max(1, run.train.replay_capacity // run.resources.num_replay_shards),
                                           frame_shape, 1 + run.game.n_followers, run.game.frame_stack,
                                           seed=run.train.seed + i, prioritized=run.train.prioritized)
                        for i in range(run.resources.num_replay_shards)]
        # driver_bytes: pickled size of all that rollout actors and the learner returned to the driver
        # updates_skipped: what the replay ratio owed while a restarted replay refilled (never run)
        self.counters = {"env_steps": 0, "updates": 0, "episodes": 0, "weights_pushed_at": 0, "driver_bytes": 0,
                         "next_eval_at": run.eval.every_env_steps, "updates_skipped": 0,
                         "rollout_actor_restarts": 0, "replay_restarts": 0}
        self.last_eval: dict = {}
        self._replay_ready = False
        self._incarnations: dict[int, str] = {}  # of each replay shard, as the learner last saw it
        self._started = time.perf_counter()
        self._share_replays()

    def _after_restore(self) -> None:
        self._push_weights()

    # -- wiring
    def _share_replays(self, runner_ids=None) -> None:
        replays = self.replays
        n = len(replays)
        self.env_runner_group.foreach_env_runner(
            lambda runner: runner.set_replay(replays[(getattr(runner, "worker_index", 0) or 0) % n]),
            remote_worker_ids=runner_ids, local_env_runner=False)
        agents = module_of_agent(self.run)
        answering = [m for m in set(agents) if answers_leader(self.run, m)]
        any_shortest, safety = self.run.train.any_shortest_move, self.run.train.safety_head
        self.learner_group.foreach_learner(
            lambda learner: learner.set_replays(replays, agents, answering, any_shortest, safety))

    def restore_env_runners(self, env_runner_group):
        restored = super().restore_env_runners(env_runner_group)
        if restored:  # a restarted actor is a fresh process: hand it the replay and the weights again
            self.counters["rollout_actor_restarts"] += len(restored)
            self._share_replays(restored)
            self._push_weights(restored)
        return restored

    def _push_weights(self, runner_ids=None) -> None:
        (ref, seq), = learner_values(self.learner_group.foreach_learner(
            lambda learner: (ray.put(learner.get_state(components=COMPONENT_RL_MODULE, inference_only=True)
                                     [COMPONENT_RL_MODULE]), learner._weights_seq_no)))
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
        if not learning or owed_ahead < lead:
            self.env_runner_group.foreach_env_runner_async("sample", tag="sample")
        for _, result in self.env_runner_group.fetch_ready_async_reqs(tags="sample", timeout_seconds=0.01):
            c["env_steps"] += result["env_steps"]
            c["driver_bytes"] += len(pickle.dumps(result))
            self._log_episodes(result["episodes"])
        owed = t.replay_ratio * c["env_steps"] - c["updates"] - c["updates_skipped"]
        if learning and owed >= 1:
            n, need = int(min(owed, updates_per_call)), self._min_records()
            results = learner_values(self.learner_group.foreach_learner(
                lambda learner, n=n, need=need: learner.pull_and_update(n, need)))
            c["driver_bytes"] += len(pickle.dumps(results))
            self.metrics.aggregate([r["metrics"] for r in results], key=LEARNER_RESULTS)
            for r in results:
                c["updates"] += r["updates"]
                self._note_incarnations(r["incarnations"])
                if r["updates"] < n:  # a replay restarted and holds too few records: wait for the refill
                    self._replay_ready = False
            if c["updates"] - c["weights_pushed_at"] >= t.weights_every_updates:
                self._push_weights()
                c["weights_pushed_at"] = c["updates"]
        elif not learning:
            time.sleep(0.01)
        if c["env_steps"] >= c["next_eval_at"]:
            self.last_eval = self.evaluate_greedy()
            c["next_eval_at"] += self.run.eval.every_env_steps
        self._log_counters()

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

    def _log_episodes(self, episodes: list[dict]) -> None:
        m = self.metrics
        for e in episodes:
            self.counters["episodes"] += 1
            for key in ("success", "reached", "collided", "broken", "truncated"):
                m.log_value(("explore", key), float(e[key]), window=500)
            m.log_value(("explore", "episode_steps"), e["steps"], window=500)
            for start in STARTS[1:]:  # the share of training episodes that started elsewhere than the spec's places
                m.log_value(("explore", f"start_{start}"), float(e["start"] == start), window=500)
            for name, value in zip(self.run.game.agent_names, e["returns"]):
                m.log_value(("explore", f"return_{name}"), value, window=500)

    def _log_counters(self) -> None:
        c = self.counters
        elapsed = time.perf_counter() - self._started
        m = self.metrics
        m.log_value("env_steps", c["env_steps"], window=1)
        m.log_value("learner_updates", c["updates"], window=1)
        m.log_value("episodes", c["episodes"], window=1)
        m.log_value(NUM_ENV_STEPS_SAMPLED_LIFETIME, c["env_steps"], window=1)
        m.log_value("session_seconds", elapsed, window=1)
        for key, value in self.last_eval.items():
            if isinstance(value, int | float):
                m.log_value(("greedy", key), value, window=1)

class StockFormationDQN(GreedyEvaluationMixin, DQN):
    """RLlib's own DQN training step (its EnvRunners, episode replay buffer and DQN loss) on the
    same game, modules and replay ratio: the reference the data path is measured against."""

    def setup(self, config) -> None:
        super().setup(config)
        self.run = config.run
        self.counters = {"env_steps": 0, "updates": 0, "episodes": 0, "driver_bytes": 0,
                         "next_eval_at": self.run.eval.every_env_steps}
        self.last_eval: dict = {}
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
        if c["env_steps"] >= c["next_eval_at"]:
            self.last_eval = self.evaluate_greedy()
            c["next_eval_at"] += self.run.eval.every_env_steps


def _frame_shape(run: RunConfig) -> tuple[int, int, int]:
    obs_space, _ = spaces_of(run)
    h, w, c = obs_space.shape
    return (h, w, c // run.game.frame_stack)
