"""Diagnostic: how well can a Q-network's encoder imitate the teacher's labels, offline?

    .venv/bin/python experiments/imitation_probe.py collect --states 50000 --seed 11 --out /tmp/probe_11.npz
    .venv/bin/python experiments/imitation_probe.py collect --states 50000 --seed 12 --out /tmp/probe_12.npz
    .venv/bin/python experiments/imitation_probe.py fit /tmp/probe_1[12].npz --net flat [--iterations 8000]
    .venv/bin/python experiments/imitation_probe.py fit /tmp/probe_1[12].npz --net window --forecast [--row-scan 16]
    .venv/bin/python experiments/imitation_probe.py fit /tmp/probe_1[12].npz --net window --forecast --agents 1 \
        --loss margin --leader-labels sets

``collect`` plays setting-1 games (grid observations, 2 stacked frames) that follow the teacher's
joint label except, with probability ``--explore`` per step, a random joint move (so states off the
teacher's path are met too, as DAgger meets them), and keeps every labelled state. ``fit`` trains
one network per agent with cross-entropy on the labels of the first 80% of the games and prints
the per-step agreement with the labels on the last 20%: the imitation accuracy a network can reach
with unlimited updates, which the RL runs' greedy agreement (experiments/teacher_agreement.py)
can be set against. ``collect`` also keeps every state's joint actions that start a shortest path;
``fit --leader-labels sets`` lets the leader learn any of its moves among them (``train.any_shortest_move``),
and every fit reports how often the leader's move is one of them. ``--loss margin``: DQfD's large margin,
as the learner uses, instead of cross-entropy.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch import nn

from formation.config import GameConfig
from formation.game import BatchedGame, Observer
from formation.learn.qnet import DuelingQNetwork, large_margin_sets
from formation.learn.teacher import Teacher


def collect(args: argparse.Namespace) -> None:
    config = GameConfig.from_setting(args.setting, obs_type="grid", frame_stack=2)
    teacher = Teacher(config, slack=6, order="lockstep", robust_first_step=True)
    games = 32
    game = BatchedGame(config, games, seed=args.seed)
    game.reset()
    observer = Observer(game)
    obs = observer.observe(np.ones(games, bool)).copy()
    rng = np.random.default_rng(args.seed)
    episode = np.arange(games)
    next_episode = games
    xs, ys, eps, sets, start = [], [], [], [], time.time()
    n = 0
    while n < args.states:
        actions = rng.integers(0, 4, (games, 2))
        actions[:, 1] = np.where(rng.random(games) < 0.5, actions[:, 0], actions[:, 1])
        for i in range(games):
            joint = teacher.label(game.scenario(i), first_step=game.steps[i] == 0)
            if joint is None:
                continue
            xs.append(obs[i])
            ys.append(joint)
            sets.append(acceptable(teacher, game.scenario(i), joint, game.steps[i] == 0))
            eps.append(episode[i])
            n += 1
            if rng.random() >= args.explore:
                actions[i] = joint
        game.step(actions)
        done = game.done.copy()
        if done.any():
            game.reset(mask=done)
            for i in np.flatnonzero(done):
                episode[i], next_episode = next_episode, next_episode + 1
        obs = observer.observe(done).copy()
    print(f"{n} labelled states from {next_episode} episodes in {time.time() - start:.0f} s", flush=True)
    np.savez_compressed(args.out, obs=np.stack(xs), labels=np.array(ys, np.int64), episodes=np.array(eps),
                        acceptable=np.stack(sets))


def acceptable(teacher: Teacher, scenario, joint: tuple[int, ...], first_step: bool) -> np.ndarray:
    """(16,) bool: the joint actions (4 * leader's move + follower's move) that start a shortest
    path; only the label on a first step (the robust label)."""
    mask = np.zeros(16, bool)
    if first_step:
        mask[4 * joint[0] + joint[1]] = True
        return mask
    for leader, follower in teacher._starts(scenario) or [joint]:
        mask[4 * leader + follower] = True
    return mask


def fit(args: argparse.Namespace) -> None:
    torch.manual_seed(0)
    parts = [np.load(path) for path in args.data]
    obs, labels = np.concatenate([p["obs"] for p in parts]), np.concatenate([p["labels"] for p in parts])
    sets = torch.from_numpy(np.concatenate([p["acceptable"] for p in parts]).reshape(-1, 4, 4))
    leader_ok = sets.any(2)  # (N, 4): the leader's moves that start a shortest path with some follower move
    episodes = np.concatenate([p["episodes"] + 1_000_000 * k for k, p in enumerate(parts)])
    train = episodes < np.quantile(episodes, 0.8)
    x_train, y_train = torch.from_numpy(obs[train]), torch.from_numpy(labels[train])
    x_test, y_test = torch.from_numpy(obs[~train]), torch.from_numpy(labels[~train])
    ok_train, ok_test = leader_ok[torch.from_numpy(train)], leader_ok[torch.from_numpy(~train)]
    print(f"{len(x_train)} training states, {len(x_test)} test states; "
          f"labels F/FL/FR/S of the leader: {np.bincount(labels[:, 0], minlength=4) / len(labels)}", flush=True)
    shape = obs.shape[1:]
    nets = [make_net(args.net, shape, args, agent) for agent in range(args.agents)]
    print(f"{sum(p.numel() for p in nets[0].parameters())} parameters per net", flush=True)
    optims = [torch.optim.Adam(n.parameters(), lr=args.lr) for n in nets]
    rng = np.random.default_rng(0)
    start = time.time()
    for it in range(1, args.iterations + 1):
        idx = torch.from_numpy(rng.integers(0, len(x_train), args.batch))
        for agent, (net, opt) in enumerate(zip(nets, optims)):
            logits = net(x_train[idx])
            accepted = ok_train[idx] if agent == 0 and args.leader_labels == "sets" else \
                nn.functional.one_hot(y_train[idx, agent], 4).bool()
            if args.loss == "margin":  # DQfD's large margin (the learner's), towards any accepted move
                loss = large_margin_sets(logits, accepted, 1.0).mean()
            else:  # cross-entropy of the accepted moves' summed probability
                loss = (logits.logsumexp(1) - logits.masked_fill(~accepted, -1e9).logsumexp(1)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        if it % args.report == 0:
            with torch.no_grad():
                test = [torch.cat([net(x).argmax(1) for x in x_test.split(2048)]) for net in nets]
                train_pred = [net(x_train[:len(x_test)]).argmax(1) for net in nets]
            right = [(p == y_test[:, a]) for a, p in enumerate(test)]
            right_train = [(p == y_train[:len(x_test), a]).float().mean().item() for a, p in enumerate(train_pred)]
            on_path = ok_test[torch.arange(len(x_test)), test[0]].float().mean()
            follower = (f"follower {right[1].float().mean():.4f} both {(right[0] & right[1]).float().mean():.4f}; "
                        if len(right) > 1 else "")
            print(f"it {it}: test agreement leader {right[0].float().mean():.4f} "
                  f"(a shortest path's move: {on_path:.4f}) {follower}train "
                  f"{min(right_train):.4f}+; {time.time() - start:.0f} s", flush=True)


class Centred(nn.Module):
    """The grid shifted so that one agent sits at its centre ((2H-1) x (2W-1), a board plane added),
    then the usual encoder and dueling heads."""

    def __init__(self, shape, plane: int, hidden: int, channels, window=None):
        super().__init__()
        h, w, c = shape
        self.h, self.w, self.plane = h, w, plane
        # window: rows above, rows below, columns either side of the agent (default: the whole board)
        self.up, self.down, self.side = window or (h - 1, h - 1, w - 1)
        self.q = DuelingQNetwork((self.up + self.down + 1, 2 * self.side + 1, c + 1), 1, hidden=hidden,
                                 channels=channels)

    def forward(self, obs):
        n, h, w, c = obs.shape
        x = obs.float()
        where = x[:, :, :, self.plane].reshape(n, -1).argmax(1)
        r, col = where // w, where % w
        board = torch.ones(n, h, w, 1)
        x = nn.functional.pad(torch.cat([x, board], 3), (0, 0, self.side, self.side, self.up, self.down))
        rows = (r[:, None] + torch.arange(self.up + self.down + 1))[:, :, None]
        cols = (col[:, None] + torch.arange(2 * self.side + 1))[:, None, :]
        crop = x[torch.arange(n)[:, None, None], rows, cols]
        return self.q(crop)


def make_net(name: str, shape: tuple[int, int, int], args: argparse.Namespace, agent: int) -> nn.Module:
    if name == "flat":
        return DuelingQNetwork(shape, 1, hidden=args.hidden, channels=tuple(args.channels))
    if name in ("centred-leader", "centred-self"):  # grid planes: destination, obstacles, followers, leader
        plane = shape[2] - 1 if name == "centred-leader" or agent == 0 else shape[2] - 2
        return Centred(shape, plane, args.hidden, tuple(args.channels), args.window)
    if name == "window":  # the training's own network: the leader window, with the options of train.*
        return DuelingQNetwork(shape, 1, hidden=args.hidden, channels=tuple(args.channels),
                               window=tuple(args.window or (12, 3, 10)), frame_channels=4,
                               forecast=args.forecast, row_scan=args.row_scan)
    raise SystemExit(f"--net: {name!r} is not allowed; allowed: flat, centred-leader, centred-self, window")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--states", type=int, default=60_000)
    c.add_argument("--explore", type=float, default=0.1)
    c.add_argument("--setting", type=int, default=1)
    c.add_argument("--seed", type=int, default=11)
    c.add_argument("--out", default="/tmp/probe.npz")
    f = sub.add_parser("fit")
    f.add_argument("data", nargs="+", help="files written by collect")
    f.add_argument("--net", default="flat")
    f.add_argument("--iterations", type=int, default=6000)
    f.add_argument("--batch", type=int, default=128)
    f.add_argument("--lr", type=float, default=1e-3)
    f.add_argument("--hidden", type=int, default=128)
    f.add_argument("--channels", type=int, nargs=3, default=[16, 32, 32])
    f.add_argument("--window", type=int, nargs=3, help="rows above, rows below, columns either side")
    f.add_argument("--report", type=int, default=1000)
    f.add_argument("--forecast", action="store_true", help="--net window: with train.obstacle_forecast")
    f.add_argument("--row-scan", type=int, default=0, help="--net window: train.row_scan planes")
    f.add_argument("--loss", default="cross-entropy", choices=("cross-entropy", "margin"))
    f.add_argument("--agents", type=int, default=2, choices=(1, 2), help="1: the leader's network only")
    f.add_argument("--leader-labels", default="label", choices=("label", "sets"),
                   help="sets: the leader learns to pick any move that starts a shortest path")
    args = p.parse_args()
    torch.set_num_threads(1)
    collect(args) if args.command == "collect" else fit(args)


if __name__ == "__main__":
    main()
