"""The learner: pulls batches from the replay actor itself and updates every agent's DQN.

It runs inside RLlib's LearnerGroup (a Ray actor, on a GPU when the config asks), so batches go
replay actor -> learner without passing the driver. The next batch is requested before the
current one is used (prefetch), so the learner rarely waits on the replay. On a CPU the modules
(leader, follower) update in parallel threads, one core each, after the layers without weights have
read each batch's screens once for both.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import ray
import torch
from ray.rllib.algorithms.dqn.dqn_learner import QF_NEXT_PREDS, QF_PREDS, QF_TARGET_NEXT_PREDS
from ray.rllib.algorithms.dqn.torch.dqn_torch_learner import DQNTorchLearner
from ray.rllib.core.columns import Columns
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from formation.game.core import joint_mask_bits
from formation.learn.module import PREPARED_NEXT_OBS, PREPARED_OBS, SAFETY_LOGITS
from formation.learn.qnet import N_ACTIONS, double_q_target, large_margin_sets

RETURNS, DISCOUNTS, LABELS, WEIGHTS = "n_step_returns", "n_step_discounts", "teacher_labels", "weights"
ACCEPTED = "teacher_accepted"  # train.any_shortest_move: the moves the margin accepts, bools beside LABELS
SAFE = "safe_joint_moves"  # train.safety_horizon: (N, 16) bools, the joint moves that start safe steps


def module_batches(sample: dict[str, np.ndarray], module_of_agent: list[str],
                   answering: frozenset[str] = frozenset(), any_shortest_move: str = "none", safety: bool = False
                   ) -> dict[str, dict[str, np.ndarray]]:
    """Split a replay sample (all agents) into one batch per module; agents that share a module
    (followers with one policy) contribute one row each for every sampled step. A module in
    ``answering`` (it answers the leader) gets actions as pairs with the leader's move, ``4 * leader +
    own`` (its Q-values' index), and labels as one own move per move of the leader, (N, 4): the
    sample's ``answers`` where it has them, its label in the row of the move the leader made, -1 where
    there is none. With ``any_shortest_move`` "leader" (one follower), the leader's module also gets
    ``ACCEPTED``, (N, 4) bools: every move of the leader that the sample's ``accepted`` joint actions hold
    (with any follower move), and the label's move. With ``safety`` every module gets ``SAFE``, the sample's
    ``safe`` joint moves as (N, 16) bools (leader's move, follower's move, row by row), one row per agent of
    the module."""
    rows: dict[str, list[int]] = {}
    for agent, module in enumerate(module_of_agent):
        rows.setdefault(module, []).append(agent)
    leader = sample["actions"][:, 0].astype(np.int64)
    out = {}
    for module, agents in rows.items():
        shared = {key: _repeat(sample[key], len(agents)) for key in ("obs", "next_obs", "discounts", "weights")}
        actions = [sample["actions"][:, a] for a in agents]
        labels = [sample["labels"][:, a] for a in agents]
        if module in answering:
            actions = [N_ACTIONS * leader + a for a in actions]
            labels = [_answer_rows(sample, a, leader) for a in agents]
        out[module] = {Columns.OBS: shared["obs"], Columns.NEXT_OBS: shared["next_obs"],
                       Columns.ACTIONS: np.concatenate(actions),
                       RETURNS: np.concatenate([sample["returns"][:, a] for a in agents]),
                       DISCOUNTS: shared["discounts"], LABELS: np.concatenate(labels), WEIGHTS: shared["weights"]}
        if any_shortest_move == "leader" and agents == [0]:
            out[module][ACCEPTED] = _accepted_moves(sample["accepted"], labels[0])
        if safety:
            out[module][SAFE] = _repeat(joint_mask_bits(sample["safe"]).reshape(len(leader), -1), len(agents))
    return out


def _accepted_moves(accepted: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The leader's accepted moves, (N, 4) bools (see ``module_batches``): those that start a shortest path
    with some follower move, and each label's move (``labels`` (N,))."""
    moves = joint_mask_bits(accepted).any(2)  # (N, leader's move, follower's move) -> the leader's
    return moves | ((labels[:, None] == np.arange(N_ACTIONS)) & (labels[:, None] >= 0))


def _answer_rows(sample: dict[str, np.ndarray], agent: int, leader: np.ndarray) -> np.ndarray:
    """(N, 4): ``agent``'s teacher move for each move of the leader (-1: none), its label in the row of
    the move the leader made."""
    n = len(leader)
    rows = sample["answers"][:, agent].copy() if "answers" in sample else np.full((n, N_ACTIONS), -1, np.int64)
    label = sample["labels"][:, agent]
    taught = np.flatnonzero(label >= 0)
    rows[taught, leader[taught]] = label[taught]
    return rows


def _margin(q: torch.Tensor, accepted: torch.Tensor, gap: float) -> tuple[torch.Tensor, torch.Tensor]:
    """DQfD's J_E = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), a_E the teacher's (planner's) action, per step of a
    module batch, summed over its labelled rows; with several ``accepted`` moves (N, rows, moves), Q(s, a_E)
    is the best of theirs. Also whether each step has a labelled row. A row with none accepts all: no loss."""
    taught_rows = accepted.any(2)
    moves = accepted.shape[2]
    rows = large_margin_sets(q.reshape(-1, moves), (accepted | ~taught_rows[..., None]).reshape(-1, moves), gap)
    return (rows.view(len(q), -1) * taught_rows).sum(1), taught_rows.any(1)


def _label_moves(labels: torch.Tensor, n_q: int) -> torch.Tensor:
    """(N, rows, moves) bools: each labelled row's label move (none where the label is -1). Rows: 1 (of
    ``n_q``, the module's Q-values), or 4 for a module that answers the leader (one per move of the leader)."""
    labels = labels.long()
    moves = n_q if labels.dim() == 1 else N_ACTIONS
    accepted = torch.nn.functional.one_hot(labels.clamp(min=0), moves).bool() & (labels >= 0)[..., None]
    return accepted if accepted.dim() == 3 else accepted.unsqueeze(1)


def _accepted_rows(accepted: torch.Tensor) -> torch.Tensor:
    """A module batch's ``ACCEPTED`` as (N, rows, moves) bools."""
    accepted = accepted.bool()
    return accepted if accepted.dim() == 3 else accepted.unsqueeze(1)


def _repeat(a: np.ndarray, copies: int) -> np.ndarray:
    """``a`` once per agent of a module; the array itself (no copy) for a module of one agent."""
    return a if copies == 1 else np.concatenate([a] * copies)


class FormationLearner(DQNTorchLearner):
    _replays: list = []
    _threads: ThreadPoolExecutor | None = None
    module_threads = True  # False: RLlib's serial update (the same arithmetic, one module after the other)

    def _uncompiled_update(self, batch: dict, **kwargs):
        """RLlib's update, but on a CPU each module's forward and backward pass runs in its own thread:
        the modules share no parameters, and torch's kernels release the GIL, so two modules train on
        two cores at once. Gradients are then clipped and applied as RLlib does."""
        modules = list(batch.keys())
        if not self.module_threads or len(modules) < 2 or self._device is None or self._device.type != "cpu":
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

    def _prepare_once(self, batch: dict) -> None:
        """Run the layers without weights (``DuelingQNetwork.prepare``) once for each distinct tensor of
        observations of the batch, not once per module and network: the leader's and the follower's
        modules read the same screens. Each result goes into every module batch that holds that tensor,
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
                    any_shortest_move: str = "none", safety: bool = False) -> bool:
        """The replay shards to pull from, each agent's module, the modules that answer the leader, whether
        the margin accepts every move that starts a shortest path (``train.any_shortest_move``), and whether
        the modules learn a safety head."""
        self._replays = list(handles)
        self._module_of_agent = list(module_of_agent)
        self._answering = frozenset(answering)
        self._any_shortest_move = any_shortest_move
        self._safety = safety
        self._prefetch = None
        self._turn = 0
        self._priority: dict[str, np.ndarray] = {}
        self._stats: dict[str, dict[str, float]] = {}
        self.num_updates = getattr(self, "num_updates", 0)
        return True

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any],
                                fwd_out: dict[str, Any]) -> torch.Tensor:
        q = fwd_out[QF_PREDS]
        actions = batch[Columns.ACTIONS].long().unsqueeze(1)
        q_taken = q.gather(1, actions).squeeze(1)
        with torch.no_grad():
            y = double_q_target(batch[RETURNS], batch[DISCOUNTS], fwd_out[QF_NEXT_PREDS], fwd_out[QF_TARGET_NEXT_PREDS])
        td = q_taken - y
        loss = (batch[WEIGHTS] * torch.nn.functional.smooth_l1_loss(q_taken, y, reduction="none")).mean()
        priority = td.detach().abs()
        if config.margin > 0:
            labelled = _label_moves(batch[LABELS], q.shape[1])
            if ACCEPTED not in batch:
                large_margin, taught = _margin(q, labelled, config.margin_gap)
            else:  # every accepted move
                large_margin, taught = _margin(q, _accepted_rows(batch[ACCEPTED]), config.margin_gap)
            if taught.any():
                loss = loss + config.margin * large_margin[taught].mean()
                # prioritized replay also revisits the states where the module disagrees with the teacher
                priority = priority + config.margin * (large_margin.detach() * taught)
        # logged by pull_and_update, in one thread (RLlib's metrics logger is not thread-safe)
        self._stats[module_id] = {"q_mean": q_taken.detach().mean().item(),
                                  "td_abs_mean": td.detach().abs().mean().item()}
        if SAFE in batch and SAFETY_LOGITS in fwd_out:
            logits, safe = fwd_out[SAFETY_LOGITS], batch[SAFE].float()
            safety = torch.nn.functional.binary_cross_entropy_with_logits(logits, safe)
            loss = loss + config.safety_weight * safety
            wrong = (logits.detach() > 0) != safe.bool()
            self._stats[module_id].update(safety_loss=safety.item(), safety_error=wrong.float().mean().item())
        self._priority[module_id] = priority.cpu().numpy()
        return loss

    def _request(self, batch_size: int, n_step: int, gamma: float, min_records: int):
        index = self._turn % len(self._replays)
        self._turn += 1
        return index, self._replays[index].sample.remote(batch_size, n_step, gamma, min_records)

    def pull_and_update(self, num_updates: int, min_records: int = 1) -> dict:
        """Run up to ``num_updates`` updates on batches pulled from the replay. Returns the reduced
        ``metrics``, the ``updates`` run, and the ``incarnations`` of the replays seen (index ->
        id). It stops early when a replay holds fewer than ``min_records`` (it restarted empty)."""
        cfg = self.config
        done, seen = 0, {}
        for _ in range(num_updates):
            if self._prefetch is None:
                self._prefetch = self._request(cfg.train_batch_size, cfg.n_step, cfg.gamma, min_records)
            index, ref = self._prefetch
            sample = ray.get(ref)
            self._prefetch = None
            if sample is None:  # the replay is refilling after a restart
                break
            self._prefetch = self._request(cfg.train_batch_size, cfg.n_step, cfg.gamma, min_records)
            incarnation = seen[index] = sample.pop("incarnation")
            batches = module_batches(sample, self._module_of_agent, self._answering,
                                     self._any_shortest_move, self._safety)
            n = len(sample["ids"])
            batch = MultiAgentBatch({m: SampleBatch(b) for m, b in batches.items()}, env_steps=n)
            # DQNLearner syncs target networks by this count: ours counts learner updates.
            self.update(batch=batch, timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: self.num_updates},
                        _no_metrics_reduce=True)
            self.num_updates += 1
            done += 1
            for module_id, stats in self._stats.items():
                for key, value in stats.items():
                    self.metrics.log_value((module_id, key), value, window=1)
            if cfg.prioritized:
                priority = np.stack([self._priority[m].reshape(-1, n).max(0) for m in batches]).max(0)
                self._replays[index].update_priorities.remote(sample["ids"], priority, incarnation)
        return {"metrics": self.metrics.reduce(), "updates": done, "incarnations": seen}

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
