"""The RLlib module of one agent: a dueling Q-network with a target copy (``DuelingQModule``).

It implements RLlib's ``QNetAPI`` and ``TargetNetworkAPI``, so RLlib's DQN learner (the stock
path) and ours both train it, and ``InferenceOnlyAPI``, so rollout actors get weights without
the target network. ``model_config``: ``network``, the network's ``NetworkSpec.to_dict()``
(``formation.recipe.team.network_specs``), ``epsilon``, and ``average_decay``: a learner's module also keeps the
moving average of the network's weights (``train.average_decay``), the team that is evaluated and exported.
Its observation space is what it acts on; a network that reads screens per cell also takes their cells (the
formation path's replay batches hold only those), so the learner's batches may differ from that space in height and
width.
Every module acts in the env's actions, 0..3. A module that answers the leader has 16 Q-values, one per (leader's
move, own move) as ``4 * leader + own``; alone, without the leader's move, its ``forward_inference`` and
``forward_exploration`` return the own move of its best pair. The formation path's rollout actors and evaluation read
its Q-values instead and take the row of the move the leader makes (``formation.recipe.qnet.team_q_values``).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.dqn.dqn_learner import QF_NEXT_PREDS, QF_PREDS, QF_TARGET_NEXT_PREDS
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, QNetAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.torch import TorchRLModule
from ray.rllib.utils.schedules.scheduler import Scheduler

from formation.recipe.collect import epsilon_greedy
from formation.recipe.learn import average_into, forward
from formation.recipe.loss import ROLE
from formation.recipe.qnet import N_ACTIONS, NetworkSpec

# a batch's observations as DuelingQNetwork.prepare makes them, when the learner prepared them already
PREPARED_OBS, PREPARED_NEXT_OBS = "prepared_obs", "prepared_next_obs"
SAFETY_LOGITS = "safety_logits"  # a network with a safety head: its (N, 16) logits (teacher.safety_horizon)


class DuelingQModule(TorchRLModule, InferenceOnlyAPI, TargetNetworkAPI, QNetAPI):
    def setup(self) -> None:
        cfg = self.model_config or {}
        self.q_network = NetworkSpec.from_dict(cfg["network"]).build()
        # RLlib's DQNConfig puts an epsilon schedule into every module's model_config.
        self.epsilon_schedule = Scheduler(fixed_value_or_schedule=cfg.get("epsilon", 0.05), framework="torch")
        self._rng = np.random.default_rng()
        self._average_decay = cfg.get("average_decay", 0.0)
        self._averaged_q_network = None
        if self._average_decay and not self.inference_only:
            self._averaged_q_network = copy.deepcopy(self.q_network).requires_grad_(False)

    # -- QNetAPI
    def compute_q_values(self, batch: dict[str, Any]) -> dict[str, Any]:
        return {QF_PREDS: self.q_network(batch[Columns.OBS])}

    # -- TargetNetworkAPI
    def make_target_networks(self) -> None:
        self._target_q_network = make_target_network(self.q_network)

    def get_target_network_pairs(self):
        return [(self.q_network, self._target_q_network)]

    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        return {QF_PREDS: self._target_q_network(batch[Columns.OBS])}

    def update_average(self) -> None:
        """After a learner update: one step of the moving average of the network's weights, if the module keeps one
        (``formation.recipe.learn.average_into``)."""
        if self._averaged_q_network is not None:
            average_into(self._averaged_q_network, self.q_network, self._average_decay)

    # -- InferenceOnlyAPI
    def get_non_inference_attributes(self) -> list[str]:
        return ["_target_q_network", "_averaged_q_network"]

    # -- forward passes
    def greedy_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The env action (0..3) of the best Q-value; of a network that answers the leader, the own move of its
        best (leader's move, own move) pair."""
        return self.q_network(obs).argmax(dim=-1) % N_ACTIONS

    def _forward_inference(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        return {Columns.ACTIONS: self.greedy_actions(batch[Columns.OBS])}

    def _forward_exploration(self, batch: dict[str, Any], t: int = 0, **kwargs) -> dict[str, Any]:
        """RLlib's EnvRunners (the stock path): each agent on its own, the recipe's ``epsilon_greedy``."""
        greedy = self.greedy_actions(batch[Columns.OBS])
        self.epsilon_schedule.update(t)
        epsilon = float(self.epsilon_schedule.get_current_value())
        actions = epsilon_greedy(greedy.cpu().numpy()[:, None], epsilon, self._rng, joint=False)[:, 0]
        return {Columns.ACTIONS: torch.from_numpy(actions).to(greedy.device)}

    def _forward_train(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """``formation.recipe.learn.forward``: the layers without weights are skipped where the batch brings the
        observations prepared (``PREPARED_OBS``, ``PREPARED_NEXT_OBS``: the learner prepares once for every module
        that prepares alike)."""
        out = forward(self.q_network, self._target_q_network, batch[Columns.OBS], batch[Columns.NEXT_OBS],
                      batch.get(PREPARED_OBS), batch.get(PREPARED_NEXT_OBS), batch.get(ROLE))
        return {QF_PREDS: out["q"], QF_NEXT_PREDS: out["q_next"], QF_TARGET_NEXT_PREDS: out["q_target_next"],
                **({SAFETY_LOGITS: out["safety_logits"]} if "safety_logits" in out else {})}
