"""The learner: pulls batches from the replay actor itself and updates every agent's DQN, RLlib's Learner around the
recipe's update (``formation.recipe.learn.forward`` in the modules, ``formation.recipe.loss``).

It runs inside RLlib's LearnerGroup (a Ray actor, on a GPU when the config asks), so batches go
replay actor -> learner without passing the driver. The next batch is requested before the
current one is used (prefetch), so the learner rarely waits on the replay. On a CPU the modules
(leader, follower) update in parallel threads, one core each, after the layers without weights have
read each batch's observations once for both. Where the networks read screens per cell, a batch's
observations are those cells already (the replay stores only them), which the networks take as they
are (``formation.recipe.qnet.ScreenCells``); the modules' observation space stays the screen they act on.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import ray
import torch
from ray.rllib.algorithms.dqn.dqn_learner import QF_NEXT_PREDS, QF_PREDS, QF_TARGET_NEXT_PREDS
from ray.rllib.algorithms.dqn.torch.dqn_torch_learner import DQNTorchLearner
from ray.rllib.core import COMPONENT_RL_MODULE
from ray.rllib.core.columns import Columns
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from formation.recipe.learn import sample_priorities
from formation.recipe.loss import ACTIONS, NEXT_OBS, OBS, dqn_loss, module_batches
from formation.recipe.stopwatch import Stopwatch, with_size
from formation.rllib.module import PREPARED_NEXT_OBS, PREPARED_OBS, SAFETY_LOGITS

# the recipe's batches use RLlib's column names
assert (OBS, NEXT_OBS, ACTIONS) == (Columns.OBS, Columns.NEXT_OBS, Columns.ACTIONS)

def team_weights(learner) -> dict:
    """A learner's modules' inference weights as the team that is evaluated and exported plays them: each network's
    moving average where its module keeps one (``train.average_decay``), else the network's own."""
    state = learner.get_state(components=COMPONENT_RL_MODULE, inference_only=True)[COMPONENT_RL_MODULE]
    for module_id, weights in state.items():
        averaged = learner.module[module_id].unwrapped()._averaged_q_network
        if averaged is not None:
            weights.update({f"q_network.{k}": v.detach().cpu().numpy() for k, v in averaged.state_dict().items()})
    return state


class FormationLearner(DQNTorchLearner):
    _replays: list = []
    _threads: ThreadPoolExecutor | None = None
    module_threads = True  # False: RLlib's serial update (the same arithmetic, one module after the other)

    def _uncompiled_update(self, batch: dict, **kwargs):
        """RLlib's update, but on a CPU each module's forward and backward pass runs in its own thread:
        the modules share no parameters, and torch's kernels release the GIL, so two modules train on
        two cores at once. Gradients are then clipped and applied as RLlib does."""
        modules = list(batch.keys())
        # data-parallel learners: one backward pass, so every learner's gradient all-reduces come in one order
        if (not self.module_threads or self.distributed or len(modules) < 2 or self._device is None
                or self._device.type != "cpu"):
            return super()._uncompiled_update(batch, **kwargs)
        if self._threads is None:
            self._threads = ThreadPoolExecutor(len(modules), thread_name_prefix="module-update")
        self._compute_off_policyness(batch)
        for optim in self._optimizer_parameters:
            optim.zero_grad(set_to_none=True)
        self._prepare_once(batch)

        def forward_backward(module_id: str):
            fwd_out = self.module[module_id].forward_train(batch[module_id])
            config = self.config.get_config_for_module(module_id)
            loss = self.compute_loss_for_module(module_id=module_id, config=config, batch=batch[module_id],
                                                fwd_out=fwd_out)
            loss.backward()
            return fwd_out, loss

        results = dict(zip(modules, self._threads.map(forward_backward, modules)))
        gradients = {pid: p.grad for pid, p in self._params.items() if p.grad is not None}
        self.apply_gradients(self.postprocess_gradients(gradients))
        return {m: r[0] for m, r in results.items()}, {m: r[1] for m, r in results.items()}, {}

    def apply_gradients(self, gradients_dict: dict) -> None:
        """RLlib's ``apply_gradients``, with one finiteness check of all gradients at once instead of two
        per parameter tensor; RLlib's own (per tensor: ``nan`` and ``inf`` set to numbers) where one is not
        finite, or where grad scalers or torch LR schedulers are in use."""
        grads = [g for g in gradients_dict.values() if g is not None]
        plain = self._grad_scalers is None and self._lr_scheduler_classes is None
        if not plain or (grads and not bool(torch.stack(torch._foreach_norm(grads)).isfinite().all())):
            return super().apply_gradients(gradients_dict)
        for pid, grad in gradients_dict.items():
            self._params[pid].grad = grad
        for module_id, names in self._module_optimizers.items():
            for name in names:
                self.get_optimizer(module_id, name).step()

    def _prepare_once(self, batch: dict) -> None:
        """Run the layers without weights (``DuelingQNetwork.prepare``) once for each distinct tensor of
        observations of the batch, not once per module and network: the leader's and the follower's
        modules read the same observations. Each result goes into every module batch that holds that tensor,
        as ``PREPARED_OBS`` / ``PREPARED_NEXT_OBS``, which ``DuelingQModule`` then reads."""
        groups: dict[tuple, tuple[Any, torch.Tensor, list]] = {}
        for module_id, columns in batch.items():
            net = self.module[module_id].q_network
            for column, prepared in ((Columns.OBS, PREPARED_OBS), (Columns.NEXT_OBS, PREPARED_NEXT_OBS)):
                obs = columns[column]
                key = (net.prepare_key, obs.data_ptr(), obs.dtype, tuple(obs.shape), obs.stride())
                groups.setdefault(key, (net, obs, []))[2].append((module_id, prepared))

        def prepare(group: tuple) -> torch.Tensor:
            net, obs, _ = group
            with torch.no_grad():
                return net.prepare(obs)

        for (_, _, users), x in zip(groups.values(), self._threads.map(prepare, groups.values())):
            for module_id, prepared in users:
                batch[module_id][prepared] = x

    def set_replays(self, handles: list, module_of_agent: list[str], answering: list[str] = (),
                    safety: bool = False) -> bool:
        """The run's replay shards, each agent's module, the modules that answer the leader, and whether the modules
        learn a safety head. Learner ``rank`` of ``k`` pulls from shards ``rank``, ``rank + k``, ... only."""
        rank, k = (torch.distributed.get_rank(), torch.distributed.get_world_size()) if self.distributed else (0, 1)
        self._shards = list(range(len(handles)))[rank::k]
        self._replays = list(handles)
        self._module_of_agent = list(module_of_agent)
        self._answering = frozenset(answering)
        self._safety = safety
        self._prefetch = None
        self._turn = 0
        self._last = None  # the last batch: updated on again while a restarted shard refills
        self._priority: dict[str, np.ndarray] = {}
        self._stats: dict[str, dict[str, float]] = {}
        self.clock = Stopwatch()
        self.num_updates = getattr(self, "num_updates", 0)
        return True

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any],
                                fwd_out: dict[str, Any]) -> torch.Tensor:
        """``formation.recipe.loss.dqn_loss`` on the module's batch; its priorities and statistics are kept for
        ``pull_and_update``, which logs them in one thread (RLlib's metrics logger is not thread-safe)."""
        loss, priority, self._stats[module_id] = dqn_loss(
            batch, fwd_out[QF_PREDS], fwd_out[QF_NEXT_PREDS], fwd_out[QF_TARGET_NEXT_PREDS],
            safety_logits=fwd_out.get(SAFETY_LOGITS), **config.loss_weights)
        self._priority[module_id] = priority.cpu().numpy()
        return loss

    def _request(self, min_records: int):
        cfg = self.config
        index = self._shards[self._turn % len(self._shards)]
        self._turn += 1
        # RLlib's train_batch_size_per_learner: train.batch_size split over the learners
        return index, self._replays[index].sample.remote(cfg.train_batch_size_per_learner, cfg.n_step, cfg.gamma,
                                                         min_records)

    def pull_and_update(self, num_updates: int, min_records: int = 1) -> dict:
        """Run ``num_updates`` updates on batches pulled from this learner's replay shards, always that many, so that
        data-parallel learners meet at every gradient all-reduce. Returns the reduced ``metrics``, the
        ``incarnations`` of the shards seen (index -> id), and ``refilling``: a shard held fewer than
        ``min_records`` (it restarted empty), and the updates after went on the last batch pulled; the driver then
        pauses learning until the shard has refilled."""
        clock = self.clock
        seen, refilling = {}, False
        for _ in range(num_updates):
            if self._prefetch is None:
                self._prefetch = self._request(min_records)
            index, ref = self._prefetch
            with clock("wait"):  # for the replay's batch: the part of its sampling the prefetch did not hide
                sample = ray.get(ref)
            self._prefetch = None
            if sample is None:  # the shard is refilling after a restart
                refilling = True
                index, sample, incarnation = self._last or self._wait_for_batch(min_records)
            else:
                self._prefetch = self._request(min_records)
                incarnation = seen[index] = sample.pop("incarnation")
                self._last = index, sample, incarnation
            priority = self.update_on(sample)
            if priority is not None:  # (a shard that restarted since drops them: they are of its lost records)
                self._replays[index].update_priorities.remote(sample["ids"], priority, incarnation)
        with clock("batch"):
            metrics = self.metrics.reduce()
        return with_size({"metrics": metrics, "updates": num_updates, "refilling": refilling, "incarnations": seen,
                          "seconds": clock.pop()})

    def _wait_for_batch(self, min_records: int) -> tuple[int, dict, str]:
        """A batch from a shard that restarted before this learner's first update: wait for its refill."""
        while True:
            index, ref = self._request(min_records)
            sample = ray.get(ref)
            if sample is not None:
                self._last = index, sample, sample.pop("incarnation")
                return self._last
            time.sleep(0.1)

    def update_on(self, sample: dict) -> np.ndarray | None:
        """One update of every module on a replay batch (``FrameReplay.sample``); returns the batch's new
        priorities (None without ``train.prioritized``)."""
        clock = self.clock
        with clock("batch"):
            batches = module_batches(sample, self._module_of_agent, self._answering, self._safety)
            n = len(sample["ids"])
            batch = MultiAgentBatch({m: SampleBatch(b) for m, b in batches.items()}, env_steps=n)
        with clock("update"):  # RLlib's update: to the device, forward, backward, step, target sync
            # DQNLearner syncs target networks by this count: ours counts learner updates.
            self.update(batch=batch, timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: self.num_updates},
                        _no_metrics_reduce=True)
        self.num_updates += 1
        for module_id in batches:
            self.module[module_id].unwrapped().update_average()
        with clock("batch"):
            for module_id, stats in self._stats.items():
                for key, value in stats.items():
                    self.metrics.log_value((module_id, key), value, window=1)
            if not self.config.prioritized:
                return None
            return sample_priorities({m: self._priority[m] for m in batches}, n)

    def weights_ref(self) -> tuple[ray.ObjectRef, int] | None:
        """The modules' inference weights in Ray's object store, and their sequence number; None on a data-parallel
        learner other than the first (they all hold the same weights, which go out once)."""
        if self.distributed and torch.distributed.get_rank() != 0:
            return None
        weights = self.get_state(components=COMPONENT_RL_MODULE, inference_only=True)[COMPONENT_RL_MODULE]
        return ray.put(weights), self._weights_seq_no

    def get_state(self, components=None, *, not_components=None, **kwargs):
        state = super().get_state(components, not_components=not_components, **kwargs)
        # DQNLearner keeps its target-sync bookkeeping outside its state: save it ourselves.
        state["last_target_update"] = dict(self.last_update_ts_by_mid)
        state["num_updates"] = getattr(self, "num_updates", 0)
        return state

    def set_state(self, state) -> None:
        super().set_state(state)
        self.last_update_ts_by_mid.update(state.get("last_target_update", {}))
        self.num_updates = state.get("num_updates", getattr(self, "num_updates", 0))
