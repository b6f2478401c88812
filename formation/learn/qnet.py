"""The Q-network and the DQN arithmetic, in plain torch (the RLlib module and learner wrap these).

Observations arrive as uint8 ``(N, H, W, C)`` (C = frame channels x stack) and are normalised
here. The encoders are sized for CPUs: the pixel encoder's first layer reads non-overlapping
4x4 patches, so a forward pass costs about 2.4 MMAC per sample instead of the Nature DQN's 10.
"""

from __future__ import annotations

import torch
from torch import nn

N_ACTIONS = 4


def encoder(obs_shape: tuple[int, int, int], channels: tuple[int, int, int] = (16, 32, 32)) -> nn.Sequential:
    h, w, c = obs_shape
    c1, c2, c3 = channels
    if min(h, w) >= 64:  # screens: 84x84 -> 21 -> 11 -> 6
        first = nn.Conv2d(c, c1, kernel_size=4, stride=4)
    else:  # grids: one cell per entry, keep full resolution in the first layer
        first = nn.Conv2d(c, c1, kernel_size=3, stride=1, padding=1)
    return nn.Sequential(first, nn.ReLU(), nn.Conv2d(c1, c2, 3, 2, 1), nn.ReLU(), nn.Conv2d(c2, c3, 3, 2, 1),
                         nn.ReLU(), nn.Flatten())


def dueling(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Q(s, a) = V(s) + A(s, a) - mean_a' A(s, a')   (Wang et al. 2016, eq. 9; the paper's dueling head)."""
    return value + advantage - advantage.mean(dim=1, keepdim=True)


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
    a_e = labels.long().unsqueeze(1)
    margins = torch.full_like(q, gap).scatter(1, a_e, 0.0)
    return (q + margins).max(1).values - q.gather(1, a_e).squeeze(1)


class DuelingQNetwork(nn.Module):
    """uint8 observations -> Q-values of the four actions."""

    def __init__(self, obs_shape: tuple[int, int, int], high: float = 255.0, hidden: int = 128,
                 channels: tuple[int, int, int] = (16, 32, 32)):
        super().__init__()
        self.obs_shape = tuple(obs_shape)
        self.register_buffer("scale", torch.tensor(1.0 / high), persistent=False)
        self.encoder = encoder(self.obs_shape, channels)
        with torch.no_grad():
            n = self.encoder(torch.zeros(1, obs_shape[2], obs_shape[0], obs_shape[1])).shape[1]
        self.value = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        self.advantage = nn.Sequential(nn.Linear(n, hidden), nn.ReLU(), nn.Linear(hidden, N_ACTIONS))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = self.encoder(obs.permute(0, 3, 1, 2).float() * self.scale)
        return dueling(self.value(x), self.advantage(x))
