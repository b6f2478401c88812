"""The shared replay as a Ray actor: rollout actors push records, the learner pulls batches."""

from __future__ import annotations

import ray

from formation.learn.replay import Chunk, FrameReplay


@ray.remote(num_cpus=0, max_restarts=-1)
class ReplayActor:
    def __init__(self, capacity: int, frame_shape, n_agents: int, frame_stack: int, seed: int = 0,
                 prioritized: bool = False):
        self.replay = FrameReplay(capacity, frame_shape, n_agents, frame_stack, seed=seed, prioritized=prioritized)
        self.env_steps = 0  # agent steps pushed (records that are not terminal records)

    def add(self, chunk: Chunk) -> int:
        self.replay.add(chunk)
        self.env_steps += int((~chunk.terminal).sum())
        return self.env_steps

    def sample(self, batch_size: int, n_step: int, gamma: float) -> dict:
        return self.replay.sample(batch_size, n_step=n_step, gamma=gamma)

    def update_priorities(self, ids, td_errors) -> None:
        self.replay.update_priorities(ids, td_errors)

    def stats(self) -> dict:
        return {**self.replay.stats(), "replay_env_steps": self.env_steps}

    def ready(self, min_records: int) -> bool:
        return self.replay.size >= min_records
