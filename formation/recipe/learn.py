"""Updating: one learner update of every module of the team on a replay sample, in plain torch.

``forward`` is a module's pass over its batch (the online network on the observations, the network and its target
copy on the next ones); the RLlib module (``formation.rllib.module``) runs it inside RLlib's learner, and
``Learner`` runs it with its own Adam optimizers in the single-process loop (``formation.recipe.loop``). Both then
take the loss and priorities of ``formation.recipe.loss.dqn_loss``. No Ray.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from formation.recipe.config import RunConfig
from formation.recipe.loss import NEXT_OBS, OBS, ROLE, dqn_loss, module_batches
from formation.recipe.qnet import DuelingQNetwork, of_role
from formation.recipe.team import answers_leader, module_of_agent


def forward(net: DuelingQNetwork, target: DuelingQNetwork, obs: torch.Tensor, next_obs: torch.Tensor,
            x: torch.Tensor | None = None, x_next: torch.Tensor | None = None, role: torch.Tensor | None = None
            ) -> dict[str, torch.Tensor]:
    """Q-values of ``obs`` (``q``), and of ``next_obs`` by the network and its target (``q_next``, ``q_target_next``,
    no gradient), and the safety head's logits (``safety_logits``) where the network has one. ``x``, ``x_next``:
    the observations already through the layers without weights (``DuelingQNetwork.prepare``), where the caller
    prepared them once for several modules. ``role`` (N,): each row's agent, for a network several agents share
    (``NetworkSpec.roles``; the batch's ``ROLE``): the Q-values are that agent's."""
    x = net.prepare(obs) if x is None else x
    features = net.features(x)
    out = {"q": of_role(net.q_of(features), role)}
    if net.safety is not None:
        out["safety_logits"] = net.safety_logits(x, features)
    with torch.no_grad():  # targets only: no backward pass through the next observations
        x_next = net.prepare(next_obs) if x_next is None else x_next
        out["q_next"] = of_role(net.q_values(x_next), role)
        out["q_target_next"] = of_role(target.q_values(x_next), role)
    return out


def loss_weights(run: RunConfig) -> dict[str, float]:
    """``dqn_loss``'s weights of the teacher's terms (``margin``, ``margin_gap``, ``safety_weight``): the teacher
    section's, or 0 without a teacher (there are no labels to weigh)."""
    t = run.teacher
    if t is None:
        return {"margin": 0.0, "margin_gap": 0.0, "safety_weight": 0.0}
    return {"margin": t.margin, "margin_gap": t.margin_gap, "safety_weight": t.safety_weight}


def sample_priorities(per_module: dict[str, np.ndarray], n: int) -> np.ndarray:
    """A replay sample's new priorities from each module's (``dqn_loss``; a module of k agents has k rows per
    step): a step's largest, so a step any agent gets wrong comes back."""
    return np.stack([np.asarray(p).reshape(-1, n).max(0) for p in per_module.values()]).max(0)


def average_into(averaged: DuelingQNetwork, net: DuelingQNetwork, decay: float) -> None:
    """One step of the exponential moving average of ``net``'s weights kept in ``averaged``: each weight becomes
    ``decay * averaged + (1 - decay) * net`` (``train.average_decay``)."""
    with torch.no_grad():
        torch._foreach_lerp_(list(averaged.parameters()), list(net.parameters()), 1.0 - decay)


class Learner:
    """The team's networks, their target copies and Adam optimizers: ``update`` is one learner update of every
    module on a replay sample (``formation.recipe.replay.FrameReplay.sample``). With ``train.average_decay``,
    ``averaged`` holds the moving average of each network's weights after every update: the team that is
    evaluated and exported (None: the networks themselves)."""

    def __init__(self, run: RunConfig, networks: dict[str, DuelingQNetwork]):
        self.run, self.networks = run, networks
        self.targets = {m: copy.deepcopy(net).requires_grad_(False) for m, net in networks.items()}
        self.optimizers = {m: torch.optim.Adam(net.parameters(), lr=run.train.lr) for m, net in networks.items()}
        self.agent_modules = module_of_agent(run)
        self.answering = frozenset(m for m in networks if answers_leader(run, m))
        self.loss_weights = loss_weights(run)
        self.updates = 0
        self.averaged = None
        if run.train.average_decay:
            self.averaged = {m: copy.deepcopy(net).requires_grad_(False) for m, net in networks.items()}

    def state_dict(self) -> dict:
        """What ``load_state_dict`` needs to go on learning as this learner would: the update count and each
        module's network, target copy, average and Adam state (the single-process loop's checkpoint)."""
        return {"updates": self.updates, **{name: {m: part.state_dict() for m, part in modules.items()}
                                            for name, modules in self._parts.items()}}

    def load_state_dict(self, state: dict) -> None:
        """The state ``state_dict`` gave, but the learning rate this learner's run names (a resume may change it)."""
        for name, modules in self._parts.items():
            for m, part in modules.items():
                part.load_state_dict(state[name][m])
        for optimizer in self.optimizers.values():
            for group in optimizer.param_groups:
                group["lr"] = self.run.train.lr
        self.updates = int(state["updates"])

    @property
    def _parts(self) -> dict[str, dict]:
        return {"networks": self.networks, "targets": self.targets, "averaged": self.averaged or {},
                "optimizers": self.optimizers}

    def update(self, sample: dict[str, np.ndarray], game: tuple[list[str], dict, dict] | None = None
               ) -> tuple[np.ndarray, dict[str, dict[str, float]]]:
        """One update of every module; the sample's new priorities (the largest over modules) and each module's
        statistics (``dqn_loss``). ``game``: the sample's agents' modules, and networks and target networks that
        read its game (``formation.recipe.qnet.tied`` to this learner's), where it is another game of the run's
        ``games``; None: the run's own."""
        t = self.run.train
        agent_modules, networks, targets = game or (self.agent_modules, self.networks, self.targets)
        batches = module_batches(sample, agent_modules, self.answering, self.run.safety_head)
        priorities, stats = {}, {}
        for module, columns in batches.items():
            batch = {key: torch.from_numpy(np.asarray(value)) for key, value in columns.items()}
            out = forward(networks[module], targets[module], batch[OBS], batch[NEXT_OBS], role=batch[ROLE])
            loss, priority, stats[module] = dqn_loss(batch, out["q"], out["q_next"], out["q_target_next"],
                                                     safety_logits=out.get("safety_logits"), **self.loss_weights)
            optimizer = self.optimizers[module]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.networks[module].parameters(), t.grad_clip)
            optimizer.step()
            stats[module]["total_loss"] = loss.item()
            priorities[module] = priority.numpy()
        self.updates += 1
        for module, averaged in (self.averaged or {}).items():
            average_into(averaged, self.networks[module], t.average_decay)
        if self.updates % t.target_update_every == 0:  # the target copies follow every target_update_every updates
            for module, net in self.networks.items():
                self.targets[module].load_state_dict(net.state_dict())
        return sample_priorities(priorities, len(sample["ids"])), stats
