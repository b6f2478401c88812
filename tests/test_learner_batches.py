"""A replay sample of all agents becomes one batch per module; shared followers add rows."""

import numpy as np

from formation.learn.learner import DISCOUNTS, LABELS, RETURNS, module_batches


def test_followers_sharing_a_policy_each_contribute_their_own_rows():
    n = 3
    sample = {"obs": np.arange(n)[:, None, None, None] * np.ones((1, 2, 2, 1), np.uint8),
              "next_obs": np.zeros((n, 2, 2, 1), np.uint8),
              "actions": np.array([[0, 1, 2], [3, 0, 1], [2, 2, 0]]),
              "returns": np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]], np.float32),
              "discounts": np.array([0.9, 0.0, 0.81], np.float32),
              "labels": np.array([[-1, 1, 2], [3, -1, -1], [0, 0, 0]]),
              "weights": np.ones(n, np.float32)}
    batches = module_batches(sample, ["leader", "follower", "follower"])
    assert set(batches) == {"leader", "follower"}
    leader, follower = batches["leader"], batches["follower"]
    assert leader["actions"].tolist() == [0, 3, 2] and leader[RETURNS].tolist() == [1.0, 4.0, 7.0]
    assert leader[LABELS].tolist() == [-1, 3, 0]
    # follower_1's three rows, then follower_2's, each with its own action, return and label
    assert follower["actions"].tolist() == [1, 0, 2, 2, 1, 0]
    assert follower[RETURNS].tolist() == [2.0, 5.0, 8.0, 3.0, 6.0, 9.0]
    assert follower[LABELS].tolist() == [1, -1, 0, 2, -1, 0]
    # the shared screen and the discount repeat for every follower
    assert follower["obs"][:, 0, 0, 0].tolist() == [0, 1, 2, 0, 1, 2]
    np.testing.assert_allclose(follower[DISCOUNTS], [0.9, 0.0, 0.81, 0.9, 0.0, 0.81])
