"""The learning step of the recipe, in plain numpy and torch: a replay sample split into one batch per module
(``module_batches``), and the loss of one module's batch (``dqn_loss``), the paper's double dueling DQN with
DQfD's large margin towards the teacher's labels and, where the networks have one, the safety head's loss.
The RLlib learner (``formation.rllib.learner``) calls both; nothing here knows of Ray.
"""

from __future__ import annotations

import numpy as np
import torch

from formation.game.core import joint_mask_bits
from formation.recipe.qnet import N_ACTIONS

# a module batch's columns; the first three are RLlib's own names (ray.rllib.core.columns.Columns)
OBS, NEXT_OBS, ACTIONS = "obs", "new_obs", "actions"
RETURNS, DISCOUNTS, LABELS, WEIGHTS = "n_step_returns", "n_step_discounts", "teacher_labels", "weights"
ROLE = "agent_role"  # each row's agent, its index among the module's agents (formation.recipe.qnet.agent_roles)
SAFE = "safe_joint_moves"  # teacher.safety_horizon: (N, 16) bools, the joint moves that start safe steps


def module_batches(sample: dict[str, np.ndarray], module_of_agent: list[str],
                   answering: frozenset[str] = frozenset(), safety: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """Split a replay sample (all agents) into one batch per module; agents that share a module
    (followers with one policy) contribute one row each for every sampled step. A module in
    ``answering`` (it answers the leader) gets actions as pairs with the leader's move, ``4 * leader +
    own`` (its Q-values' index), and labels as one own move per move of the leader, (N, 4): the
    sample's ``answers`` where it has them, its label in the row of the move the leader made, -1 where
    there is none. Every row carries its agent's role (``ROLE``), for a network the agents share with it as input.
    With ``safety`` every module gets ``SAFE``, the sample's
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
        out[module] = {OBS: shared["obs"], NEXT_OBS: shared["next_obs"],
                       ACTIONS: np.concatenate(actions),
                       RETURNS: np.concatenate([sample["returns"][:, a] for a in agents]),
                       DISCOUNTS: shared["discounts"], LABELS: np.concatenate(labels), WEIGHTS: shared["weights"],
                       ROLE: np.repeat(np.arange(len(agents), dtype=np.int64), len(leader))}
        if safety:
            out[module][SAFE] = _repeat(joint_mask_bits(sample["safe"]).reshape(len(leader), -1), len(agents))
    return out


def _answer_rows(sample: dict[str, np.ndarray], agent: int, leader: np.ndarray) -> np.ndarray:
    """(N, 4): ``agent``'s teacher move for each move of the leader (-1: none), its label in the row of
    the move the leader made."""
    n = len(leader)
    rows = sample["answers"][:, agent].copy() if "answers" in sample else np.full((n, N_ACTIONS), -1, np.int64)
    label = sample["labels"][:, agent]
    taught = np.flatnonzero(label >= 0)
    rows[taught, leader[taught]] = label[taught]
    return rows


def _margin(q: torch.Tensor, labelled: torch.Tensor, gap: float) -> tuple[torch.Tensor, torch.Tensor]:
    """DQfD's J_E = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), a_E the teacher's (planner's) action, per step of a
    module batch, summed over its labelled rows (``labelled``, (N, rows, moves): each row's label move,
    ``_label_moves``). Also whether each step has a labelled row. A row without a label accepts all: no loss."""
    taught_rows = labelled.any(2)
    moves = labelled.shape[2]
    rows = large_margin_sets(q.reshape(-1, moves), (labelled | ~taught_rows[..., None]).reshape(-1, moves), gap)
    return (rows.view(len(q), -1) * taught_rows).sum(1), taught_rows.any(1)


def _label_moves(labels: torch.Tensor, n_q: int) -> torch.Tensor:
    """(N, rows, moves) bools: each labelled row's label move (none where the label is -1). Rows: 1 (of
    ``n_q``, the module's Q-values), or 4 for a module that answers the leader (one per move of the leader)."""
    labels = labels.long()
    moves = n_q if labels.dim() == 1 else N_ACTIONS
    accepted = torch.nn.functional.one_hot(labels.clamp(min=0), moves).bool() & (labels >= 0)[..., None]
    return accepted if accepted.dim() == 3 else accepted.unsqueeze(1)


def _repeat(a: np.ndarray, copies: int) -> np.ndarray:
    """``a`` once per agent of a module; the array itself (no copy) for a module of one agent."""
    return a if copies == 1 else np.concatenate([a] * copies)


def double_q_target(returns: torch.Tensor, discounts: torch.Tensor, q_next_online: torch.Tensor,
                    q_next_target: torch.Tensor) -> torch.Tensor:
    """y = R + gamma^n * Q_target(s', argmax_a Q_online(s', a))   (double DQN, van Hasselt et al. 2016).

    ``returns`` is the n-step discounted reward sum and ``discounts`` gamma^n, or 0 where the
    episode terminated within the n steps."""
    best = q_next_online.argmax(dim=1, keepdim=True)
    return returns + discounts * q_next_target.gather(1, best).squeeze(1)


def large_margin(q: torch.Tensor, labels: torch.Tensor, gap: float) -> torch.Tensor:
    """DQfD's J_E(Q) = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E), l = ``gap`` for a != a_E, 0 for a_E
    (Hester et al. 2018, eq. 2), per row; ``labels`` are the teacher's actions a_E (all >= 0)."""
    return large_margin_sets(q, torch.nn.functional.one_hot(labels.long(), q.shape[1]).bool(), gap)


def large_margin_sets(q: torch.Tensor, accepted: torch.Tensor, gap: float) -> torch.Tensor:
    """``large_margin`` towards a set of teacher's actions: max_a [Q(s, a) + l(a)] - max_{a in E} Q(s, a),
    l = ``gap`` for a not in E, 0 in E; ``accepted`` (bool, the shape of ``q``) marks E, at least one
    action per row. With one action in E it is ``large_margin``."""
    best_accepted = q.masked_fill(~accepted, float("-inf")).max(1).values
    return (q + gap * (~accepted)).max(1).values - best_accepted


def dqn_loss(batch: dict, q: torch.Tensor, q_next_online: torch.Tensor, q_next_target: torch.Tensor,
             margin: float, margin_gap: float, safety_logits: torch.Tensor | None = None, safety_weight: float = 1.0
             ) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """One module's loss on its batch (``module_batches``), its replay priorities, and statistics to log.
    ``q``: its Q-values of the batch's observations; ``q_next_online``, ``q_next_target``: the network's and
    its target copy's of the next observations (no gradient).

        y     = R + gamma^n Q_target(s', argmax_a Q(s', a))            double DQN (van Hasselt et al. 2016)
        J_DQ  = weight * Huber(Q(s, a) - y)                              importance weight of prioritized replay
        J_E   = max_a [Q(s, a) + l(a_E, a)] - Q(s, a_E)                 DQfD's large margin (Hester et al. 2018)
        J     = J_DQ + margin * J_E  (+ safety_weight * BCE(safety))     on the steps with a teacher's label
        p     = |Q(s, a) - y| + margin * J_E                             the replay's priority

    Q is the dueling head's (``formation.recipe.qnet.dueling``)."""
    q_taken = q.gather(1, batch[ACTIONS].long().unsqueeze(1)).squeeze(1)
    with torch.no_grad():
        y = double_q_target(batch[RETURNS], batch[DISCOUNTS], q_next_online, q_next_target)
    td = q_taken - y
    loss = (batch[WEIGHTS] * torch.nn.functional.smooth_l1_loss(q_taken, y, reduction="none")).mean()
    priority = td.detach().abs()
    if margin > 0:
        large_margin_loss, taught = _margin(q, _label_moves(batch[LABELS], q.shape[1]), margin_gap)
        if taught.any():
            loss = loss + margin * large_margin_loss[taught].mean()
            # prioritized replay also revisits the states where the module disagrees with the teacher
            priority = priority + margin * (large_margin_loss.detach() * taught)
    stats = {"q_mean": q_taken.detach().mean().item(), "td_abs_mean": td.detach().abs().mean().item()}
    if safety_logits is not None and SAFE in batch:
        safe = batch[SAFE].float()
        safety = torch.nn.functional.binary_cross_entropy_with_logits(safety_logits, safe)
        loss = loss + safety_weight * safety
        wrong = (safety_logits.detach() > 0) != safe.bool()
        stats.update(safety_loss=safety.item(), safety_error=wrong.float().mean().item())
    return loss, priority, stats
