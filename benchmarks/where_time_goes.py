"""Where training time goes: an account of every second of a training config, and the ceiling it implies.

    .venv/bin/python benchmarks/where_time_goes.py configs/quickstart.yaml [--env-steps 4000] [--set KEY=VALUE]

1. **In the run.** Trains the config as ``formation train`` does (its periodic evaluation off) from an
   untrained network, past ``train.learning_starts``, then ``--env-steps`` more, and prints the seconds
   each stage took per 1,000 env steps, summed over the processes of its kind (``rollout`` actors,
   ``replay`` shards, the ``learner``, the ``driver``), and each kind's idle time. Every process
   keeps its own clock (``formation.recipe.stopwatch``).
2. **Alone.** The same stages in this one process on one thread, nothing beside them: a rollout
   actor with the run's weights and exploration playing into a local replay, that replay's sampling,
   and a learner updating both modules one after the other on its batches (so its seconds are CPU
   seconds).
3. **The ceiling.** The cores over the summed cost of one env step alone (the learner's at the
   config's replay ratio): the env steps/s this machine could reach if every core worked on nothing
   but the stages and none waited. It prints the run's env steps/s over that ceiling.
"""

from __future__ import annotations

import argparse
import os
import time
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import ray  # noqa: E402
import torch  # noqa: E402
from ray.rllib.core import COMPONENT_RL_MODULE  # noqa: E402

from formation.cli import parse_overrides  # noqa: E402
from formation.config import ConfigError  # noqa: E402
from formation.recipe.config import RunConfig  # noqa: E402
from formation.recipe.replay import FrameReplay  # noqa: E402
from formation.recipe.stopwatch import Stopwatch, add_seconds  # noqa: E402
from formation.recipe.team import answers_leader, module_of_agent, spaces_of  # noqa: E402
from formation.rllib.algorithm import build_algorithm_config, learner_values  # noqa: E402
from formation.rllib.rollout_actor import RolloutActor  # noqa: E402

KINDS = ("rollout", "replay", "learner", "driver")


def in_the_run(run: RunConfig, env_steps: int) -> tuple[dict, float, int, int, dict]:
    """The run's account: (seconds per stage per kind, wall seconds, env steps, updates, the leader's
    and follower's weights at the end)."""
    algo = build_algorithm_config(run).build_algo()
    try:
        c = algo.counters
        # past learning_starts, and past the updates owed for the env steps before it
        while c["updates"] < max(20, 0.95 * run.train.replay_ratio * c["env_steps"]):
            algo.train()
        algo.time_account()
        start, steps0, updates0 = time.perf_counter(), c["env_steps"], c["updates"]
        while c["env_steps"] - steps0 < env_steps:
            algo.train()
        wall = time.perf_counter() - start
        account = algo.time_account()
        weights, = learner_values(algo.learner_group.foreach_learner(
            lambda learner: learner.get_state(components=COMPONENT_RL_MODULE, inference_only=True)
            [COMPONENT_RL_MODULE]))
        return account, wall, c["env_steps"] - steps0, c["updates"] - updates0, {
            "weights": weights, "env_steps": c["env_steps"]}
    finally:
        algo.stop()


def alone(run: RunConfig, env_steps: int, trained: dict) -> dict:
    """Each stage's seconds for ``env_steps`` env steps, in this process, one thread."""
    torch.set_num_threads(1)
    config = build_algorithm_config(run)
    actor = RolloutActor(config=config, worker_index=1)
    actor.set_state({COMPONENT_RL_MODULE: trained["weights"], "num_env_steps_sampled_lifetime": trained["env_steps"]})
    actor.clock.pop()
    # the frames the actor records, as the run's replay stores them (a screen's cells, where the networks read them)
    replay = FrameReplay(run.train.replay_capacity, actor.rollout.frame_shape, actor.rollout.n_agents,
                         run.game.frame_stack, seed=0, prioritized=run.train.prioritized)
    inserts, clock = Stopwatch(), Stopwatch()

    def insert(chunk) -> None:
        with inserts("insert"):
            replay.add(chunk)

    actor.set_replay(SimpleNamespace(add=SimpleNamespace(remote=insert)))
    seconds: dict[str, float] = {}
    done = 0
    while done < env_steps or replay.size < run.train.batch_size:
        result = actor.sample()
        done += result["env_steps"]
        add_seconds(seconds, result["seconds"])
    account = {"rollout": seconds, "replay": {}, "learner": {}}

    learner = config.build_learner(spaces={m: spaces_of(run) for m in set(module_of_agent(run))})
    learner.module_threads = False  # one module after the other: its seconds are CPU seconds
    agents = module_of_agent(run)
    learner.set_replays([], agents, [m for m in set(agents) if answers_leader(run, m)],
                        run.safety_head)
    updates = max(1, round(run.train.replay_ratio * done))
    t = run.train
    for i in range(updates + 3):
        if i == 3:  # the first updates build RLlib's and torch's caches
            learner.clock.pop()
            clock.pop()
        with clock("sample"):
            batch = replay.sample(t.batch_size, n_step=t.n_step, gamma=t.gamma)
        priority = learner.update_on(batch)
        if priority is not None:
            with clock("priorities"):
                replay.update_priorities(batch["ids"], priority)
    account["learner"] = learner.clock.pop()
    account["replay"] = {**inserts.pop(), **clock.pop()}
    return {"account": account, "env_steps": done, "updates": updates}


def per_thousand(seconds: float, env_steps: int) -> float:
    return 1000 * seconds / max(1, env_steps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="a training config, e.g. configs/quickstart.yaml")
    parser.add_argument("--env-steps", type=int, default=4000, help="env steps timed in the run and alone")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="change a setting of the config, as formation train --set")
    parser.add_argument("--cores", type=int, default=os.cpu_count() or 2, help="cores Ray may use (default: all)")
    args = parser.parse_args()
    try:
        run = RunConfig.load(args.config, {**parse_overrides(args.set), "eval.every_env_steps": 10**9,
                                           "train.total_env_steps": 10**9})
    except (ConfigError, OSError) as error:
        parser.exit(2, f"error: {args.config}: {error}\n")
    ray.init(num_cpus=args.cores, include_dashboard=False, log_to_driver=False)
    try:
        account, wall, steps, updates, trained = in_the_run(run, args.env_steps)
    finally:
        ray.shutdown()
    # printed before the stages alone, which can take minutes: a run cut short keeps its main figure
    print(f"{args.config} {' '.join(args.set)}".strip())
    print(f"in the run: {steps} env steps in {wall:.1f} s = {steps / wall:.1f} env steps/s, "
          f"{updates / wall:.2f} learner updates/s ({updates / max(1, steps):.4f} per env step); "
          f"{run.resources.num_rollout_actors} rollout actor(s) x {run.resources.games_per_actor} games, "
          f"{args.cores} cores", flush=True)
    lone = alone(run, args.env_steps, trained)
    lone_steps = lone["env_steps"]
    # the learner alone ran the updates of lone_steps env steps at the config's replay ratio
    print(f"{'stage':<22} {'in the run':>11} {'alone':>8}   (seconds per 1,000 env steps)")
    total_alone = 0.0
    processes = {"rollout": run.resources.num_rollout_actors, "replay": run.resources.num_replay_shards,
                 "learner": 1, "driver": 1}
    for kind in KINDS:
        stages = sorted(set(account.get(kind, {})) | set(lone["account"].get(kind, {})))
        busy = 0.0
        for stage in stages:
            ran = per_thousand(account.get(kind, {}).get(stage, 0.0), steps)
            by_itself = lone["account"].get(kind, {}).get(stage)
            idle_stage = (kind, stage) in (("learner", "wait"), ("driver", "fetch"), ("driver", "learner"))
            busy += 0.0 if idle_stage else ran
            cell = f"{per_thousand(by_itself, lone_steps):8.2f}" if by_itself is not None else f"{'':>8}"
            if by_itself is not None and not idle_stage:
                total_alone += per_thousand(by_itself, lone_steps)
            print(f"{kind + ': ' + stage:<22} {ran:11.2f} {cell}" + ("   (waiting)" if idle_stage else ""))
        idle = per_thousand(processes[kind] * wall, steps) - busy
        print(f"{kind + ': other/idle':<22} {idle:11.2f}")
    ceiling = args.cores * 1000 / total_alone
    achieved = steps / wall
    print(f"summed cost alone: {total_alone:.2f} s per 1,000 env steps; ceiling on {args.cores} cores: "
          f"{ceiling:.1f} env steps/s; achieved {achieved:.1f} = {100 * achieved / ceiling:.0f}% of the ceiling")


if __name__ == "__main__":
    main()
