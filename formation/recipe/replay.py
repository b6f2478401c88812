"""Replay that stores each frame once and builds frame stacks and n-step returns at sample time.

Rollouts push *records*, one per game per step, in each game's own order. A record holds the
frame the agents saw before acting, every agent's action and reward, and whether the step ended
the episode. When an episode is truncated, the frame after its last step is pushed as a
*terminal record* (no action; never sampled as a start) to bootstrap from; a terminated episode
needs none. So an episode of L steps costs L or L + 1 frames, and the k-frame stacks of
consecutive steps share their frames instead of copying them. A frame is what the rollouts record:
a grid, a screen, or where the networks read screens per cell only those cells
(``formation.recipe.rollout.GameRollout``), so the stacks it samples are of that frame too.

Each record gets a global id (insertion count); slot = id % capacity. A record keeps the ids of
its predecessor and successor in the same episode; when the ring overwrites a record its slot's
id changes, so a stale link is detected by comparing ids. The predecessor of an episode's first
record is itself, which makes the stack at a reset the first frame repeated (spec 'Screen').

Nothing here knows of Ray or torch; ``formation.rllib.replay_actor`` wraps it as a Ray actor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from formation.game.core import MOVES

NONE = -1


@dataclass
class Chunk:
    """Records from one rollout, in order within each stream (a stream is one game of one actor).

    ``streams`` (N,) int: stream id of each record; ``frames`` (N, h, w, c) uint8; ``first`` (N,)
    bool: the record starts an episode; ``terminal`` (N,) bool: a terminal record (the frame
    after the last step, no action); ``actions`` (N, A) int; ``rewards`` (N, A) float;
    ``terminated`` / ``truncated`` (N,) bool: this record's step ended the episode that way.
    ``labels`` (N, A) int, optional: a teacher's action for each agent in this state (the
    planner's, for demonstrations and DAgger), -1 where there is none. ``answers`` (N, A, M) int,
    optional: each agent's teacher action if the leader made each of its M moves
    (``teacher.answer_every_leader_move``), -1 where there is none. ``safe`` (N,) int, optional: the joint actions
    that start ``teacher.safety_horizon`` steps free of failure, as a bit mask
    (``formation.planner.surviving_first_moves_many``), 0 where there is none.
    """

    streams: np.ndarray
    frames: np.ndarray
    first: np.ndarray
    terminal: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    labels: np.ndarray | None = None
    answers: np.ndarray | None = None
    safe: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.streams)


class FrameReplay:
    """Uniform (or prioritized) replay over steps of all agents at once."""

    def __init__(self, capacity: int, frame_shape: tuple[int, int, int], n_agents: int, frame_stack: int,
                 seed: int | None = None, prioritized: bool = False, alpha: float = 0.6):
        self.capacity = capacity
        self.frame_shape = tuple(frame_shape)
        self.n_agents = n_agents
        self.frame_stack = frame_stack
        self.rng = np.random.default_rng(seed)
        self.frames = np.zeros((capacity, *frame_shape), np.uint8)
        self.ids = np.full(capacity, NONE, np.int64)
        self.prev = np.full(capacity, NONE, np.int64)
        self.next = np.full(capacity, NONE, np.int64)
        self.actions = np.zeros((capacity, n_agents), np.int8)
        self.rewards = np.zeros((capacity, n_agents), np.float32)
        self.terminated = np.zeros(capacity, bool)
        self.truncated = np.zeros(capacity, bool)
        self.terminal = np.zeros(capacity, bool)
        self.labels = np.full((capacity, n_agents), -1, np.int8)
        self.answers = np.full((capacity, n_agents, len(MOVES)), -1, np.int8)
        self.safe = np.zeros(capacity, np.uint16)  # one bit per joint action of a leader and one follower
        self.added = 0  # records ever added; the next record's id
        self._stream_last: dict[int, int] = {}
        self.prioritized = prioritized
        self.alpha = alpha
        self._priority = SumTree(capacity) if prioritized else None
        self._max_priority = 1.0

    # ------------------------------------------------------------------ adding
    def add(self, chunk: Chunk) -> None:
        n = len(chunk)
        if n == 0:
            return
        if n > self.capacity:
            raise ValueError(f"replay: a chunk of {n} records exceeds the capacity {self.capacity}")
        ids = self.added + np.arange(n, dtype=np.int64)
        slots = ids % self.capacity
        self.added += n
        self.ids[slots] = ids
        self.frames[slots] = chunk.frames
        self.actions[slots] = chunk.actions
        self.rewards[slots] = chunk.rewards
        self.terminated[slots] = chunk.terminated
        self.truncated[slots] = chunk.truncated
        self.terminal[slots] = chunk.terminal
        self.labels[slots] = chunk.labels if chunk.labels is not None else -1
        self.answers[slots] = chunk.answers if chunk.answers is not None else -1
        self.safe[slots] = chunk.safe if chunk.safe is not None else 0
        self.next[slots] = NONE
        # Link each record to the previous record of its stream (itself at an episode start).
        prev = np.empty(n, np.int64)
        streams = chunk.streams.tolist()
        first = chunk.first.tolist()
        last = self._stream_last
        for i, (s, f) in enumerate(zip(streams, first)):
            p = int(ids[i]) if f else last.get(s, int(ids[i]))
            prev[i] = p
            if p != ids[i] and self.ids[p % self.capacity] == p:  # never touch a slot reused since
                self.next[p % self.capacity] = ids[i]
            last[s] = int(ids[i])
        self.prev[slots] = prev
        if self._priority is not None:
            self._priority.set(slots, np.where(chunk.terminal, 0.0, self._max_priority ** self.alpha))

    @property
    def size(self) -> int:
        return min(self.added, self.capacity)

    def stats(self) -> dict[str, float]:
        out = {"replay_records": self.size, "replay_added": self.added,
               "replay_fill": self.size / self.capacity, "replay_bytes": self.nbytes,
               "replay_bytes_per_record": self.nbytes / self.capacity}
        if self._priority is not None:
            out["replay_max_priority"] = self._max_priority
        return out

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.frames, self.ids, self.prev, self.next, self.actions, self.rewards,
                                      self.terminated, self.truncated, self.terminal, self.labels,
                                      self.answers, self.safe))

    # ------------------------------------------------------------------ reading
    def _valid(self, ids: np.ndarray) -> np.ndarray:
        ok = ids >= 0
        return ok & (self.ids[np.where(ok, ids, 0) % self.capacity] == ids)

    def stack(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The k-frame stacks ending at records ``ids``, (N, h, w, c*k) oldest first, and whether
        every frame of each stack is still in the ring."""
        k = self.frame_stack
        chain = np.empty((len(ids), k), np.int64)
        chain[:, k - 1] = ids
        ok = self._valid(ids)
        for j in range(k - 2, -1, -1):
            p = self.prev[chain[:, j + 1] % self.capacity]
            chain[:, j] = p
            ok &= self._valid(p)
        frames = self.frames[chain % self.capacity]  # (N, k, h, w, c)
        n, _, h, w, c = frames.shape
        return np.ascontiguousarray(frames.transpose(0, 2, 3, 1, 4)).reshape(n, h, w, k * c), ok

    def n_step(self, ids: np.ndarray, n: int, gamma: float):
        """n-step returns from records ``ids``: (returns (N, A), discounts (N,), next ids (N,), ok (N,)).

        The discount is gamma^m after m steps, 0 when the episode terminated inside them; after a
        truncation the next state is the terminal record (bootstrapped). ``ok`` is False where a
        link is missing (a successor not yet added or already overwritten)."""
        N = len(ids)
        returns = np.zeros((N, self.n_agents), np.float32)
        discount = np.ones(N, np.float64)
        cur = ids.copy()
        ok = self._valid(ids) & ~self.terminal[ids % self.capacity]
        running = ok.copy()
        for _ in range(n):
            slot = cur % self.capacity
            returns += (discount[:, None] * self.rewards[slot]) * running[:, None]
            nxt = self.next[slot]
            # a terminated step never bootstraps: it needs no successor (its next stack is unused)
            ended = self.terminated[slot]
            nxt = np.where(ended & ~self._valid(nxt), cur, nxt)
            ok &= ~running | self._valid(nxt)
            term = running & ended
            discount = np.where(running, discount * gamma, discount)
            discount[term] = 0.0
            cur = np.where(running, nxt, cur)
            # a step that ended the episode stops the sum; the next record is then terminal
            running &= ~(self.terminated[slot] | self.truncated[slot]) & ok
        return returns, discount.astype(np.float32), cur, ok

    def sample(self, batch_size: int, n_step: int = 1, gamma: float = 0.99, beta: float = 0.4) -> dict:
        """A batch of transitions for all agents: obs and next_obs stacks, actions, n-step returns,
        discounts (0 after termination), teacher labels, answers, safe joint actions, and ids /
        importance weights for priorities."""
        if self.size == 0:
            raise ValueError("replay: sample() on an empty replay")
        picked_ids = []
        got = 0
        for _ in range(64):
            ids = self._draw(2 * batch_size)
            returns, discounts, next_ids, ok = self.n_step(ids, n_step, gamma)
            ok &= self._stack_ok(ids) & self._stack_ok(np.where(ok, next_ids, ids))
            ids = ids[ok][: batch_size - got]
            picked_ids.append(ids)
            got += len(ids)
            if got >= batch_size:
                break
        ids = np.concatenate(picked_ids)
        if len(ids) < batch_size:
            raise ValueError("replay: too few complete transitions to sample from yet")
        returns, discounts, next_ids, _ = self.n_step(ids, n_step, gamma)
        obs, _ = self.stack(ids)
        next_obs, _ = self.stack(next_ids)
        slots = ids % self.capacity
        batch = {"obs": obs, "next_obs": next_obs, "actions": self.actions[slots].astype(np.int64),
                 "returns": returns, "discounts": discounts, "labels": self.labels[slots].astype(np.int64),
                 "answers": self.answers[slots].astype(np.int64), "safe": self.safe[slots].astype(np.int64), "ids": ids}
        if self._priority is not None:
            p = self._priority.get(slots) / self._priority.total
            weights = (self.size * p) ** (-beta)
            batch["weights"] = (weights / weights.max()).astype(np.float32)
        else:
            batch["weights"] = np.ones(len(ids), np.float32)
        return batch

    def _stack_ok(self, ids: np.ndarray) -> np.ndarray:
        ok = self._valid(ids)
        cur = ids
        for _ in range(self.frame_stack - 1):
            cur = self.prev[np.where(ok, cur, 0) % self.capacity]
            ok &= self._valid(cur)
        return ok

    def _draw(self, n: int) -> np.ndarray:
        if self._priority is not None:
            slots = self._priority.find(self.rng.random(n) * self._priority.total)
        else:
            slots = self.rng.integers(0, self.size, n)
        return self.ids[slots]

    def update_priorities(self, ids: np.ndarray, td_errors: np.ndarray, eps: float = 1e-3) -> None:
        if self._priority is None:
            return
        ok = self._valid(ids)
        p = np.abs(td_errors[ok]) + eps
        self._max_priority = max(self._max_priority, float(p.max(initial=0.0)))
        self._priority.set(ids[ok] % self.capacity, p ** self.alpha)


class SumTree:
    """Priorities in a binary sum tree: set and find in O(log n), vectorised over many slots."""

    def __init__(self, capacity: int):
        self.leaves = 1
        while self.leaves < capacity:
            self.leaves *= 2
        self.tree = np.zeros(2 * self.leaves, np.float64)

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def get(self, slots: np.ndarray) -> np.ndarray:
        return self.tree[slots + self.leaves]

    def set(self, slots: np.ndarray, values: np.ndarray) -> None:
        nodes = np.asarray(slots) + self.leaves
        self.tree[nodes] = values
        nodes = np.unique(nodes // 2)
        while len(nodes) and nodes[0] >= 1:
            self.tree[nodes] = self.tree[2 * nodes] + self.tree[2 * nodes + 1]
            if nodes[0] == 1:
                break
            nodes = np.unique(nodes // 2)

    def find(self, values: np.ndarray) -> np.ndarray:
        """Leaf slots where the prefix sums cross ``values``."""
        nodes = np.ones(len(values), np.int64)
        values = np.minimum(values, np.nextafter(self.total, 0))
        while nodes[0] < self.leaves:
            left = 2 * nodes
            go_right = values >= self.tree[left]
            values = np.where(go_right, values - self.tree[left], values)
            nodes = np.where(go_right, left + 1, left)
        return nodes - self.leaves
