"""Learner update cost: one double-DQN update of both modules (leader and follower), in plain torch.

    .venv/bin/python benchmarks/learner_update.py [--updates 40] [--device cuda]

For setting 1 from grid observations (2 stacked frames, batch 64: the quickstart) and from pixels
(4 stacked screens, batch 32: the throughput benchmark), prints milliseconds per update with the
modules one after the other (RLlib's order) and in two threads at once (``FormationLearner`` on a
CPU); each with the whole observation and the widths of configs/paper.yaml, and with the default
recipe's network (a leader window, wider layers; from pixels, reading the screen one pixel per cell as
the default does, and in 4x4-pixel patches), and with the obstacle forecast (``train.obstacle_forecast``).
Each torch op runs on one thread, as in the learner's Ray actor; ``--device cuda`` times the same
updates on a GPU (``resources.num_gpus_per_learner: 1``). No Ray: the data path's own cost is the difference to
``benchmarks/train_throughput.py``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor

import torch

from formation.game import BatchedGame, Observer
from formation.recipe.config import RunConfig
from formation.recipe.loss import double_q_target
from formation.recipe.qnet import NetworkSpec
from formation.recipe.team import network_specs


def ms_per_update(spec: NetworkSpec, batch: int, threads: int, updates: int, device: torch.device) -> float:
    shape = spec.obs_shape
    nets = [spec.build().to(device) for _ in range(2)]
    targets = [copy.deepcopy(net) for net in nets]
    optimizers = [torch.optim.Adam(net.parameters(), 1e-3) for net in nets]
    obs = torch.randint(0, 2, (batch, *shape), dtype=torch.uint8, device=device)
    next_obs = torch.randint(0, 2, (batch, *shape), dtype=torch.uint8, device=device)
    actions = torch.randint(0, 4, (batch, 1), device=device)
    returns, discounts = torch.randn(batch, device=device), torch.full((batch,), 0.9, device=device)

    def update(i: int) -> None:
        q = nets[i](obs).gather(1, actions).squeeze(1)
        with torch.no_grad():
            y = double_q_target(returns, discounts, nets[i](next_obs), targets[i](next_obs))
        optimizers[i].zero_grad()
        torch.nn.functional.smooth_l1_loss(q, y).backward()
        torch.nn.utils.clip_grad_norm_(nets[i].parameters(), 10.0)
        optimizers[i].step()

    pool = ThreadPoolExecutor(2)

    def both() -> None:
        if threads == 1:
            update(0)
            update(1)
        else:
            list(pool.map(update, [0, 1]))

    for _ in range(5):
        both()
    synchronize = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    synchronize()
    start = time.perf_counter()
    for _ in range(updates):
        both()
    synchronize()
    return (time.perf_counter() - start) / updates * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=40)
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    args = parser.parse_args()
    device = torch.device(args.device)
    torch.set_num_threads(1)
    print(f"device: {torch.cuda.get_device_name(device) if device.type == 'cuda' else 'cpu, one thread per op'}")
    print(f"{'observation':<42} {'batch':>5} {'one after the other':>20} {'two threads':>12} {'speed-up':>9}")
    for obs_type, stack, batch in (("grid", 2, 64), ("pixels", 4, 32)):
        run = RunConfig.from_dict({"game": {"setting": 1, "obs_type": obs_type, "frame_stack": stack}})
        shape = Observer(BatchedGame(run.game, batch_size=1)).shape

        def leader(run: RunConfig = run, **train) -> NetworkSpec:  # the run's leader network, these settings changed
            return network_specs(dataclasses.replace(run, train=dataclasses.replace(run.train, **train)))["leader"]

        # configs/paper.yaml's widths, the whole screen
        small = leader(channels=(16, 32, 32), hidden=128, leader_window=None, screen_cells=False,
                       obstacle_forecast=False)
        variants = [("", small), (", window", leader(obstacle_forecast=False)),
                    (", window, forecast", leader())]  # the default
        if obs_type == "pixels":  # the default reads cells; the patches it read before
            variants = [("", small), (", window, cells", variants[1][1]),
                        (", window, patches", leader(obstacle_forecast=False, screen_cells=False)),
                        (", window, cells, forecast", variants[2][1])]
        for name, spec in variants:
            serial = ms_per_update(spec, batch, 1, args.updates, device)
            threaded = ms_per_update(spec, batch, 2, args.updates, device)
            print(f"{obs_type + ' ' + 'x'.join(map(str, shape)) + name:<42} {batch:>5} {serial:>17.1f} ms "
                  f"{threaded:>9.1f} ms {serial / threaded:>8.2f}x")


if __name__ == "__main__":
    main()
