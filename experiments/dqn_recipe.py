"""Recipe search: a single-process parallel double dueling DQN on the batched game core.

Not the product (that runs on RLlib, ``formation train``): a small, fast, readable learner to
find out which training recipe makes the formation reach the destination, on 2 CPU cores.

    .venv/bin/python experiments/dqn_recipe.py --setting 1 --gamma 0.97 --n-step 3 \
        --shaping 1 --steps 300000 --out runs/recipe/a.jsonl

Each agent (leader, follower) has its own double dueling DQN; both see the same observation.
Prints and writes (JSON lines) greedy success on held-out scenarios as training goes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from formation.config import GameConfig
from formation.game import BatchedGame, Observer

EVAL_SEED = 10**6  # evaluation scenarios never used in training


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--setting", type=int, default=1, help="1-4, or 0 for plain defaults with --set")
    p.add_argument("--set", action="append", default=[], help="game override key=value (ints/floats/str)")
    p.add_argument("--obs", default="grid", choices=["grid", "pixels"])
    p.add_argument("--stack", type=int, default=2)
    p.add_argument("--gamma", type=float, default=0.97)
    p.add_argument("--n-step", type=int, default=3)
    p.add_argument("--shaping", type=float, default=1.0, help="weight of the potential-based shaping")
    p.add_argument("--potential", default="distance", choices=["distance", "planner"],
                   help="distance: -(leader's steps to the destination ignoring obstacles); "
                        "planner: -(the planner's shortest remaining path), for both agents")
    p.add_argument("--planner-slack", type=int, default=6)
    p.add_argument("--random-starts", type=float, default=0.0,
                   help="probability that a training episode starts with the formation shifted up a random number "
                        "of rows (exploring starts); evaluation always uses the spec's starts")
    p.add_argument("--dagger", action="store_true",
                   help="label every visited state with the planner's joint action (DAgger); the margin loss "
                        "(--margin) then pulls each agent's greedy action towards its label")
    p.add_argument("--team-reach", action="store_true",
                   help="followers' training reward also gets the leader's reach bonus (a team goal)")
    p.add_argument("--demo", type=float, default=0.0, help="fraction of games played by the planner")
    p.add_argument("--margin", type=float, default=0.0, help="DQfD large-margin loss weight on planner steps")
    p.add_argument("--steps", type=int, default=300_000)
    p.add_argument("--envs", type=int, default=32)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--width", type=int, default=32, help="conv channels (first layer half of it)")
    p.add_argument("--replay-ratio", type=float, default=0.125, help="updates per env step")
    p.add_argument("--replay", type=int, default=100_000)
    p.add_argument("--learning-starts", type=int, default=5_000)
    p.add_argument("--target-every", type=int, default=1_000, help="updates between target syncs")
    p.add_argument("--eps-start", type=float, default=1.0)
    p.add_argument("--eps-end", type=float, default=0.05)
    p.add_argument("--eps-steps", type=int, default=100_000)
    p.add_argument("--eval-every", type=int, default=25_000)
    p.add_argument("--eval-episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="")
    return p.parse_args()


# ---------------------------------------------------------------------------- the Q-network
class DuelingQNetwork(nn.Module):
    """uint8 observation (N, H, W, C) -> Q-values (N, 4); dueling: Q = V + A - mean(A)."""

    def __init__(self, obs_shape: tuple[int, int, int], high: float, width: int = 32):
        super().__init__()
        w2 = width
        h, w, c = obs_shape
        self.scale = 1.0 / high
        if h == 84:  # the paper's screen: Nature-DQN "valid" convolutions
            self.conv = nn.Sequential(nn.Conv2d(c, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
                                      nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten())
        else:
            self.conv = nn.Sequential(nn.Conv2d(c, w2 // 2, 3, 1, 1), nn.ReLU(), nn.Conv2d(w2 // 2, w2, 3, 2, 1),
                                      nn.ReLU(), nn.Conv2d(w2, w2, 3, 2, 1), nn.ReLU(), nn.Flatten())
        n = self.conv(torch.zeros(1, c, h, w)).shape[1]
        self.value = nn.Sequential(nn.Linear(n, 4 * w2), nn.ReLU(), nn.Linear(4 * w2, 1))
        self.advantage = nn.Sequential(nn.Linear(n, 4 * w2), nn.ReLU(), nn.Linear(4 * w2, 4))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = self.conv(obs.permute(0, 3, 1, 2).float() * self.scale)
        a = self.advantage(x)
        return self.value(x) + a - a.mean(dim=1, keepdim=True)


# ---------------------------------------------------------------------------- replay
class Replay:
    """Uniform replay of n-step transitions for all agents at once."""

    def __init__(self, capacity: int, obs_shape, n_agents: int):
        self.obs = np.zeros((capacity, *obs_shape), np.uint8)
        self.next_obs = np.zeros((capacity, *obs_shape), np.uint8)
        self.actions = np.zeros((capacity, n_agents), np.int64)
        self.returns = np.zeros((capacity, n_agents), np.float32)
        self.discounts = np.zeros(capacity, np.float32)  # gamma^n, or 0 after termination
        self.expert = np.zeros(capacity, bool)
        self.labels = np.full((capacity, n_agents), -1, np.int64)  # planner's action, -1 if none
        self.capacity, self.size, self.head = capacity, 0, 0

    def add(self, obs, actions, returns, discounts, next_obs, expert, labels):
        n = len(obs)
        idx = (self.head + np.arange(n)) % self.capacity
        self.obs[idx], self.next_obs[idx], self.actions[idx] = obs, next_obs, actions
        self.returns[idx], self.discounts[idx], self.expert[idx] = returns, discounts, expert
        self.labels[idx] = labels
        self.head = (self.head + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch: int, rng):
        idx = rng.integers(0, self.size, batch)
        return (self.obs[idx], self.actions[idx], self.returns[idx], self.discounts[idx],
                self.next_obs[idx], self.expert[idx], self.labels[idx])


class NStep:
    """Per-game queues turning 1-step transitions into n-step ones (truncation bootstraps)."""

    def __init__(self, n: int, gamma: float):
        self.n, self.gamma = n, gamma
        self.queues: dict[int, list] = {}

    def push(self, game: int, obs, actions, rewards, next_obs, terminated: bool, truncated: bool, expert, labels):
        q = self.queues.setdefault(game, [])
        q.append((obs, actions, rewards, (expert, labels)))
        out = []
        if len(q) == self.n or terminated or truncated:
            while q:
                ret = np.zeros_like(rewards)
                for k, (_, _, r, _) in enumerate(q):
                    ret = ret + (self.gamma ** k) * r
                disc = 0.0 if terminated else self.gamma ** len(q)
                o, a, _, (e, lab) = q[0]
                out.append((o, a, ret, disc, next_obs, e, lab))
                q.pop(0)
                if not (terminated or truncated):
                    break
        return out


# ---------------------------------------------------------------------------- evaluation
def greedy_success(config: GameConfig, nets, episodes: int, seed: int) -> dict:
    game = BatchedGame(config, batch_size=episodes, seed=seed)
    game.reset()
    observer = Observer(game)
    obs = observer.observe(np.ones(episodes, bool))
    live = np.ones(episodes, bool)
    success = np.zeros(episodes, bool)
    steps = np.zeros(episodes, int)
    collided = np.zeros(episodes, bool)
    broken = np.zeros(episodes, bool)
    with torch.no_grad():
        while live.any():
            o = torch.from_numpy(obs)
            actions = np.stack([net(o).argmax(1).numpy() for net in nets], axis=1)
            game.step(actions)
            newly = live & game.done
            success |= newly & game.success
            collided |= newly & game.collided.any(1)
            broken |= newly & ~game.formation_kept
            steps[newly] = game.steps[newly]
            live &= ~game.done
            obs = observer.observe(np.zeros(episodes, bool))
    return {"success": float(success.mean()), "collision": float(collided.mean()),
            "broken": float(broken.mean()), "steps_success": float(steps[success].mean()) if success.any() else 0.0}


# ---------------------------------------------------------------------------- training
def main() -> None:
    args = parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    overrides = {}
    for kv in args.set:
        k, v = kv.split("=")
        overrides[k] = int(v) if v.lstrip("-").isdigit() else (float(v) if "." in v else v)
    config = GameConfig.from_setting(args.setting or None, obs_type=args.obs, frame_stack=args.stack, **overrides)
    B = args.envs
    game = BatchedGame(config, batch_size=B, seed=args.seed)

    def shift_starts(mask: np.ndarray) -> None:
        """Exploring starts: move the formation of some freshly reset games up by a random number
        of rows, unless that puts an agent on an obstacle or the leader on the destination row."""
        for i in np.flatnonzero(mask):
            if rng.random() >= args.random_starts:
                continue
            rows = int(rng.integers(1, game.positions[i, :, 0].min() + 1))
            moved = game.positions[i].copy()
            moved[:, 0] -= rows
            obstacles = set(zip(game.obstacle_rows[i].tolist(), game.obstacle_cols[i].tolist()))
            if moved[0, 0] <= 0 or any((r, c) in obstacles for r, c in moved.tolist()):
                continue
            game.positions[i] = moved

    game.reset()
    if args.random_starts:
        shift_starts(np.ones(B, bool))
    observer = Observer(game)
    obs = observer.observe(np.ones(B, bool)).copy()
    A = game.n_agents
    nets = [DuelingQNetwork(observer.shape, observer.high, args.width) for _ in range(A)]
    targets = [DuelingQNetwork(observer.shape, observer.high, args.width) for _ in range(A)]
    for t, n in zip(targets, nets):
        t.load_state_dict(n.state_dict())
    optims = [torch.optim.Adam(n.parameters(), lr=args.lr) for n in nets]
    replay = Replay(args.replay, observer.shape, A)
    nstep = NStep(args.n_step, args.gamma)
    dest = np.array(config.destination)

    dead = float(config.height + config.width)  # steps-to-go assigned to a lost game
    capped: dict[int, GameConfig] = {}

    def potential() -> np.ndarray:
        """Phi(s) per game: minus the steps still needed (the shaping is gamma*Phi(s') - Phi(s))."""
        if args.potential == "distance":  # the leader's steps to the destination, ignoring obstacles
            return -np.abs(game.positions[:, 0] - dest).max(axis=1).astype(np.float32)
        from formation.planner import lower_bound, shortest_path

        phi = np.zeros(B, np.float32)
        for i in range(B):
            if game.reached[i] and game.success[i]:
                continue
            if game.terminated[i]:
                phi[i] = -dead
                continue
            # A path longer than the bound + slack counts as lost: keeps every call fast.
            scenario = game.scenario(i)
            limit = lower_bound(scenario, config) + args.planner_slack
            if limit not in capped:
                capped[limit] = config.replace(max_steps=limit)
            path = shortest_path(scenario, config=capped[limit])
            phi[i] = -(len(path) if path is not None else dead)
        return phi

    # Planner-driven games: the first round(demo * B) games follow the clairvoyant planner.
    n_demo = int(round(args.demo * B))
    plans: dict[int, list] = {}
    if n_demo:
        from formation.planner import shortest_path

        def plan(i: int) -> None:
            plans[i] = list(shortest_path(game.scenario(i), config=config) or [])

        for i in range(n_demo):
            plan(i)

    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    log = open(args.out, "w") if args.out else None  # noqa: SIM115
    env_steps, updates, start = 0, 0, time.perf_counter()
    phi = potential()
    next_eval = args.eval_every
    episode_success, episodes_done = 0, 0
    while env_steps < args.steps:
        eps = max(args.eps_end, args.eps_start + (args.eps_end - args.eps_start) * env_steps / args.eps_steps)
        with torch.no_grad():
            o = torch.from_numpy(obs)
            actions = np.stack([net(o).argmax(1).numpy() for net in nets], axis=1)
        explore = rng.random((B, A)) < eps
        actions[explore] = rng.integers(0, 4, explore.sum())
        for i in range(n_demo):
            if plans[i]:
                actions[i] = plans[i].pop(0)
        labels = np.full((B, A), -1, np.int64)
        if args.dagger:
            from formation.planner import lower_bound, shortest_path

            for i in range(B):
                scenario = game.scenario(i)
                limit = lower_bound(scenario, config) + args.planner_slack
                if limit not in capped:
                    capped[limit] = config.replace(max_steps=limit)
                path = shortest_path(scenario, config=capped[limit])
                if path:
                    labels[i] = path[0]
        labels[:n_demo] = actions[:n_demo]
        game.step(actions)
        rewards = game.rewards.copy()
        if args.team_reach:
            rewards[:, 1:] += (config.reward_reach * game.reached)[:, None]
        phi_next = potential()
        shaped = args.shaping * (args.gamma * phi_next - phi)
        if args.potential == "distance":
            rewards[:, 0] += shaped
        else:
            rewards += shaped[:, None]
        done = game.done.copy()
        term, trunc = game.terminated.copy(), game.truncated.copy()
        episodes_done += done.sum()
        episode_success += (done & game.success).sum()
        if done.any():
            game.reset(mask=done)
            if args.random_starts:
                shift_starts(done)
            for i in np.flatnonzero(done[:n_demo]):
                plan(int(i))
        phi = potential() if done.any() else phi_next
        # the observation after the step (before reset) is the n-step target's next state
        next_obs = observer.observe(done).copy()
        # For games that were reset, next_obs shows the new episode; the terminal next state is
        # only bootstrapped from when truncated, which is rare (200 steps): we store the fresh
        # observation there too and accept that small bias in this experiment.
        batch = []
        for i in range(B):
            batch += nstep.push(i, obs[i], actions[i], rewards[i], next_obs[i], bool(term[i]), bool(trunc[i]),
                                i < n_demo, labels[i])
        if batch:
            o_, a_, r_, d_, n_, e_, l_ = map(np.array, zip(*batch))
            replay.add(o_, a_, r_, d_, n_, e_, l_)
        obs = next_obs
        env_steps += B
        # learner: keep updates / env steps at the replay ratio
        while replay.size >= args.learning_starts and updates < env_steps * args.replay_ratio:
            o_, a_, r_, d_, n_, e_, l_ = replay.sample(args.batch, rng)
            o_t, n_t = torch.from_numpy(o_), torch.from_numpy(n_)
            d_t = torch.from_numpy(d_)
            for k in range(A):
                q = nets[k](o_t)
                q_a = q.gather(1, torch.from_numpy(a_[:, k:k + 1])).squeeze(1)
                with torch.no_grad():
                    # Double DQN (van Hasselt 2016): y = r + gamma^n Q_target(s', argmax_a Q_online(s', a))
                    best = nets[k](n_t).argmax(1, keepdim=True)
                    y = torch.from_numpy(r_[:, k]) + d_t * targets[k](n_t).gather(1, best).squeeze(1)
                loss = nn.functional.smooth_l1_loss(q_a, y)
                labelled = l_[:, k] >= 0
                if args.margin and labelled.any():
                    # DQfD: J_E = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), a_E the planner's action
                    m = torch.from_numpy(labelled)
                    label = torch.from_numpy(np.maximum(l_[:, k:k + 1], 0))
                    margins = torch.full_like(q, 0.8).scatter(1, label, 0.0)
                    large_margin = (q + margins).max(1).values - q.gather(1, label).squeeze(1)
                    loss = loss + args.margin * large_margin[m].mean()
                optims[k].zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(nets[k].parameters(), 10.0)
                optims[k].step()
            updates += 1
            if updates % args.target_every == 0:
                for t, n in zip(targets, nets):
                    t.load_state_dict(n.state_dict())
        if env_steps >= next_eval or env_steps >= args.steps:
            next_eval += args.eval_every
            ev = greedy_success(config, nets, args.eval_episodes, EVAL_SEED)
            elapsed = time.perf_counter() - start
            row = {"env_steps": env_steps, "updates": updates, "seconds": round(elapsed, 1), "eps": round(eps, 3),
                   "explore_success": round(episode_success / max(episodes_done, 1), 3), **ev}
            episode_success = episodes_done = 0
            print(json.dumps(row), flush=True)
            if log:
                log.write(json.dumps({**vars(args), **row}) + "\n")
                log.flush()


if __name__ == "__main__":
    main()
