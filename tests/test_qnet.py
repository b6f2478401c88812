"""The DQN arithmetic against hand computations, and the network's input handling."""

import torch

from formation.learn.qnet import DuelingQNetwork, double_q_target, dueling, large_margin


def test_dueling_aggregation_by_hand():
    value = torch.tensor([[1.0], [-2.0]])
    advantage = torch.tensor([[1.0, 2.0, 3.0, 6.0], [0.0, 0.0, 4.0, 0.0]])
    # mean advantages 3 and 1
    expected = torch.tensor([[-1.0, 0.0, 1.0, 4.0], [-3.0, -3.0, 1.0, -3.0]])
    assert torch.equal(dueling(value, advantage), expected)


def test_double_q_target_by_hand():
    returns = torch.tensor([1.0, 2.0, 3.0])
    discounts = torch.tensor([0.5, 0.25, 0.0])  # the third transition terminated
    online = torch.tensor([[0.0, 9.0, 1.0, 2.0], [5.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 7.0]])
    target = torch.tensor([[10.0, 20.0, 30.0, 40.0], [8.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 100.0]])
    # the online net picks actions 1, 0, 3; the target net values them 20, 8, 100
    y = double_q_target(returns, discounts, online, target)
    assert torch.allclose(y, torch.tensor([1.0 + 0.5 * 20, 2.0 + 0.25 * 8, 3.0]))


def test_large_margin_by_hand():
    q = torch.tensor([[1.0, 4.0, 2.0, 0.0], [3.0, 1.0, 0.0, 0.0], [2.0, 1.5, 0.0, 0.0]])
    labels = torch.tensor([0, 0, 0])
    # row 1: another action is 3 above the label's, plus the gap 5; row 2: the label leads by 2, less
    # than the gap, so 5 - 2 remains; row 3: the label leads by 0.5
    assert torch.allclose(large_margin(q, labels, 5.0), torch.tensor([3.0 + 5.0, 3.0, 4.5]))
    # a label that leads by more than the gap costs nothing
    assert torch.allclose(large_margin(q, labels, 0.8), torch.tensor([3.8, 0.0, 0.3]))


def test_network_takes_uint8_screens_and_grids():
    for shape, high in (((84, 84, 12), 255), ((25, 25, 8), 1)):
        net = DuelingQNetwork(shape, high)
        obs = torch.randint(0, high + 1, (5, *shape), dtype=torch.uint8)
        q = net(obs)
        assert q.shape == (5, 4) and q.dtype == torch.float32
        # normalisation: a screen scaled to the other range gives other values
        assert not torch.allclose(net(obs), net(obs // 2))
