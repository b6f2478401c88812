"""Diagnostic: can the Q-network imitate the clairvoyant planner? (supervised, no RL)

    .venv/bin/python experiments/behaviour_cloning.py [--samples 60000] [--iterations 3000]

Collects planner steps on random setting-1 scenarios (grid observations, 2 stacked frames),
trains one network per agent with cross-entropy on the planner's actions, and prints the
training loss and the greedy success on 200 held-out scenarios every 1000 iterations.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from formation.config import GameConfig
from formation.game import BatchedGame, Observer
from formation.learn.qnet import DuelingQNetwork
from formation.planner import shortest_path

sys.path.insert(0, str(Path(__file__).parent))
from dqn_recipe import EVAL_SEED, greedy_success  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--samples", type=int, default=60_000)
    p.add_argument("--iterations", type=int, default=3000)
    p.add_argument("--stack", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(1)
    config = GameConfig.from_setting(1, obs_type="grid", frame_stack=args.stack)
    B = 64
    game = BatchedGame(config, B, seed=5)
    game.reset()
    observer = Observer(game)
    obs = observer.observe(np.ones(B, bool)).copy()
    plans = [list(shortest_path(game.scenario(i), config=config)) for i in range(B)]
    xs, ys, start = [], [], time.time()
    while len(xs) * B < args.samples:
        actions = np.array([plans[i].pop(0) for i in range(B)])
        xs.append(obs)
        ys.append(actions)
        game.step(actions)
        done = game.done.copy()
        if done.any():
            game.reset(mask=done)
            for i in np.flatnonzero(done):
                plans[i] = list(shortest_path(game.scenario(i), config=config))
        obs = observer.observe(done).copy()
    X, Y = np.concatenate(xs), np.concatenate(ys)
    print(f"{len(X)} planner steps collected in {time.time() - start:.0f} s", flush=True)
    nets = [DuelingQNetwork(observer.shape, 1) for _ in range(2)]
    optims = [torch.optim.Adam(n.parameters(), lr=1e-3) for n in nets]
    rng = np.random.default_rng(0)
    for it in range(1, args.iterations + 1):
        idx = rng.integers(0, len(X), 128)
        x = torch.from_numpy(X[idx])
        for k in range(2):
            loss = nn.functional.cross_entropy(nets[k](x), torch.from_numpy(Y[idx, k]).long())
            optims[k].zero_grad()
            loss.backward()
            optims[k].step()
        if it % 1000 == 0:
            ev = greedy_success(config, nets, 200, EVAL_SEED)
            print(f"iteration {it}: loss {loss.item():.3f}, greedy {ev}", flush=True)


if __name__ == "__main__":
    main()
