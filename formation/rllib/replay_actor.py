"""The shared replay as a Ray actor: rollout actors push records, the learner pulls batches.

Its frames have the shape of the rollouts' records (``formation.recipe.team.replay_frame_shape``): the
cells of each screen where the networks read screens per cell, so pushes, memory and batches hold no
pixel the networks do not read.

If its process dies, Ray starts it again (``max_restarts=-1``) with the same arguments and an empty
replay, and retries the calls that were in flight (``max_task_retries=-1``), so no caller sees the
failure. Every start has a new ``incarnation``: a batch carries it, the learner notices the change,
learning pauses until the rollout actors have refilled the replay, and priorities computed on the
lost records are dropped.
"""

from __future__ import annotations

import uuid

import ray

from formation.recipe.replay import Chunk, FrameReplay
from formation.recipe.stopwatch import Stopwatch


@ray.remote(num_cpus=0, max_restarts=-1, max_task_retries=-1)
class ReplayActor:
    def __init__(self, capacity: int, frame_shape, n_agents: int, frame_stack: int, seed: int = 0,
                 prioritized: bool = False):
        self.replay = FrameReplay(capacity, frame_shape, n_agents, frame_stack, seed=seed, prioritized=prioritized)
        self.env_steps = 0  # agent steps pushed (records that are not terminal records)
        self.incarnation = uuid.uuid4().hex  # a new one after every restart: the records are gone
        self.clock = Stopwatch()

    def add(self, chunk: Chunk) -> int:
        with self.clock("insert"):
            self.replay.add(chunk)
        self.env_steps += int((~chunk.terminal).sum())
        return self.env_steps

    def sample(self, batch_size: int, n_step: int, gamma: float, min_records: int = 1) -> dict | None:
        """A batch (with this replay's ``incarnation``), or None while it holds fewer than ``min_records``."""
        if self.replay.size < max(min_records, 1):
            return None
        with self.clock("sample"):
            batch = self.replay.sample(batch_size, n_step=n_step, gamma=gamma)
        return {**batch, "incarnation": self.incarnation}

    def update_priorities(self, ids, td_errors, incarnation: str | None = None) -> None:
        if incarnation is None or incarnation == self.incarnation:  # else: the records died with a restart
            with self.clock("priorities"):
                self.replay.update_priorities(ids, td_errors)

    def seconds(self) -> dict[str, float]:
        """Seconds in each stage since the last call (``formation.recipe.stopwatch``)."""
        return self.clock.pop()

    def stats(self) -> dict:
        return {**self.replay.stats(), "replay_env_steps": self.env_steps, "incarnation": self.incarnation}

    def ready(self, min_records: int) -> bool:
        return self.replay.size >= min_records
