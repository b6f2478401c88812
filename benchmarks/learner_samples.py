"""The learner's samples per second: updates of both modules on replay batches, as training makes them.

    .venv/bin/python benchmarks/learner_samples.py [configs/setting1.yaml] [--batches 32,128,512] [--gpu]

Fills a replay from one rollout actor playing the config's game (its teacher and labels included),
then times ``FormationLearner.update_on`` (the batch split per module, moved to the learner's device,
RLlib's update: forward, loss, backward, optimizer step; the priorities back) at each batch size, on
the CPU (one thread per module) or with ``--gpu`` on the first GPU. Prints milliseconds per update
and samples (replay records) per second. The replay's sampling is left out: in training another
process does it while the learner updates.
"""

from __future__ import annotations

import argparse
import os
import time
from types import SimpleNamespace

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from formation.cli import counts  # noqa: E402
from formation.config import ConfigError  # noqa: E402
from formation.recipe.config import RunConfig  # noqa: E402
from formation.recipe.replay import FrameReplay  # noqa: E402
from formation.recipe.team import answers_leader, module_of_agent, spaces_of  # noqa: E402
from formation.rllib.algorithm import build_algorithm_config  # noqa: E402
from formation.rllib.rollout_actor import RolloutActor  # noqa: E402


def filled_replay(run: RunConfig, records: int) -> FrameReplay:
    actor = RolloutActor(config=build_algorithm_config(run), worker_index=1)
    # the frames the actor records, as the run's replay stores them (a screen's cells, where the networks read them)
    replay = FrameReplay(max(records, 1000), actor.rollout.frame_shape, actor.rollout.n_agents,
                         run.game.frame_stack, seed=0, prioritized=run.train.prioritized)
    actor.set_replay(SimpleNamespace(add=SimpleNamespace(remote=replay.add)))
    while replay.size < records:
        actor.sample()
    return replay



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", nargs="?", default="configs/setting1.yaml")
    parser.add_argument("--batches", type=counts, default=[32, 128, 512], help="batch sizes, comma-separated")
    parser.add_argument("--updates", type=int, default=20, help="timed updates per batch size")
    parser.add_argument("--records", type=int, default=4000, help="records in the replay")
    parser.add_argument("--gpu", action="store_true", help="update on the first GPU")
    args = parser.parse_args()
    if args.gpu and not torch.cuda.is_available():
        parser.exit(2, "error: --gpu: torch sees no CUDA device here\n")
    torch.set_num_threads(1)
    try:
        run = RunConfig.load(args.config, {"resources.num_gpus_per_learner": 1 if args.gpu else 0})
    except (ConfigError, OSError) as error:
        parser.exit(2, f"error: {error}\n")
    replay = filled_replay(run, args.records)
    config = build_algorithm_config(run)
    agents = module_of_agent(run)
    learner = config.build_learner(spaces={m: spaces_of(run) for m in set(agents)})
    learner.set_replays([], agents, [m for m in set(agents) if answers_leader(run, m)],
                        run.safety_head)
    device = next(learner.module[agents[0]].parameters()).device
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu, one thread per module"
    print(f"{args.config}: learner on {name}; {replay.size} records in the replay")
    print(f"{'batch':>6} {'ms per update':>14} {'samples/s':>10}")
    t = run.train
    for size in args.batches:
        samples = [replay.sample(size, n_step=t.n_step, gamma=t.gamma) for _ in range(3)]
        for sample in samples:  # warm-up: caches, kernels, the optimizer's state
            learner.update_on(dict(sample))
        start = time.perf_counter()
        for i in range(args.updates):
            learner.update_on(dict(samples[i % len(samples)]))  # returns the priorities: the device has finished
        seconds = (time.perf_counter() - start) / args.updates
        print(f"{size:>6} {1000 * seconds:>14.1f} {size / seconds:>10,.0f}", flush=True)


if __name__ == "__main__":
    main()
