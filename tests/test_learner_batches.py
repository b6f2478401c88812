"""A replay sample of all agents becomes one batch per module; shared followers add rows."""

from types import SimpleNamespace

import numpy as np
import pytest

from formation.recipe.loss import DISCOUNTS, LABELS, RETURNS, ROLE, module_batches


def random_sample(rng: np.random.Generator, n: int, shape: tuple, agents: int, labelled: bool = True) -> dict:
    """A replay sample (``FrameReplay.sample``'s keys) of ``n`` random 0/1 observations of ``shape`` and ``agents``
    agents' actions, returns and labels (-1, none, unless ``labelled``)."""
    return {"obs": rng.integers(0, 2, (n, *shape), dtype=np.uint8),
            "next_obs": rng.integers(0, 2, (n, *shape), dtype=np.uint8),
            "actions": rng.integers(0, 4, (n, agents)), "returns": rng.normal(size=(n, agents)).astype(np.float32),
            "discounts": np.full(n, 0.9, np.float32),
            "labels": rng.integers(-1, 4, (n, agents)) if labelled else np.full((n, agents), -1),
            "weights": np.ones(n, np.float32)}


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
    # each row says whose it is: the role the shared network reads
    assert follower[ROLE].tolist() == [0, 0, 0, 1, 1, 1] and leader[ROLE].tolist() == [0, 0, 0]


def test_a_follower_that_answers_the_leader_gets_pairs_with_the_leaders_move():
    sample = {"obs": np.zeros((3, 2, 2, 1), np.uint8), "next_obs": np.zeros((3, 2, 2, 1), np.uint8),
              "actions": np.array([[0, 1], [3, 0], [2, 2]]), "returns": np.zeros((3, 2), np.float32),
              "discounts": np.ones(3, np.float32), "labels": np.array([[-1, 1], [3, -1], [0, 3]]),
              "weights": np.ones(3, np.float32)}
    batches = module_batches(sample, ["leader", "follower"], frozenset({"follower"}))
    assert batches["leader"]["actions"].tolist() == [0, 3, 2]  # the leader's own, unchanged
    assert batches["leader"][LABELS].tolist() == [-1, 3, 0]
    assert batches["follower"]["actions"].tolist() == [0 * 4 + 1, 3 * 4 + 0, 2 * 4 + 2]
    # a label per move of the leader: its label in the row of the move the leader made, none elsewhere
    assert batches["follower"][LABELS].tolist() == [[1, -1, -1, -1], [-1, -1, -1, -1], [-1, -1, 3, -1]]
    # with the teacher's answers to every move the leader could make, those fill the other rows
    sample["answers"] = np.array([[[-1] * 4, [1, 0, 2, -1]], [[-1] * 4, [-1] * 4], [[-1] * 4, [0, 1, 3, 2]]])
    batches = module_batches(sample, ["leader", "follower"], frozenset({"follower"}))
    assert batches["follower"][LABELS].tolist() == [[1, 0, 2, -1], [-1, -1, -1, -1], [0, 1, 3, 2]]
    assert batches["leader"][LABELS].tolist() == [-1, 3, 0]  # the leader's stay its own


def margin_loss(module: str, q, batch: dict, **config):
    """The learner's loss for one module batch whose Q-values are ``q`` (next-state Q-values 0), and its
    priorities; ``config``: margin, margin_gap and the like."""
    from types import SimpleNamespace

    import torch

    from formation.rllib.learner import FormationLearner

    n, actions = q.shape
    fwd = {"qf_preds": q, "qf_next_preds": torch.zeros(n, actions), "qf_target_next_preds": torch.zeros(n, actions)}
    learner = FormationLearner.__new__(FormationLearner)
    learner._priority, learner._stats = {}, {}
    config = SimpleNamespace(loss_weights={"safety_weight": 1.0, **config})
    loss = learner.compute_loss_for_module(module_id=module, config=config, batch=batch, fwd_out=fwd)
    return loss, learner._priority[module]


def test_the_margin_of_a_follower_that_answers_the_leader_compares_moves_in_the_leaders_row():

    import torch

    from formation.recipe.loss import WEIGHTS, large_margin

    q = torch.zeros(1, 16)
    q[0, 4 * 2 + 1] = 3.0  # in the row of leader move 2, own move 1 stands highest
    q[0, 4 * 0 + 0] = 9.0  # far higher, but in another row: it must not count
    labelled = 4 * 2 + 1
    batch = {"actions": torch.tensor([labelled]), "n_step_returns": torch.zeros(1), "n_step_discounts": torch.zeros(1),
             "teacher_labels": torch.tensor([[-1, -1, 1, -1]]), WEIGHTS: torch.ones(1)}
    loss, priority = margin_loss("follower", q, batch, margin=1.0, margin_gap=5.0)
    td = torch.nn.functional.smooth_l1_loss(torch.tensor([3.0]), torch.zeros(1))
    row = q[0, 8:12].unsqueeze(0)
    expected = td + large_margin(row, torch.tensor([1]), 5.0).mean()
    torch.testing.assert_close(loss, expected)
    # the gap (5) less the label's lead in its row (3); with the other row's 9 it would be 9 + 5 - 3
    assert large_margin(row, torch.tensor([1]), 5.0).item() == 2.0


def test_the_margin_of_every_labelled_row_counts_once_and_unlabelled_steps_not_at_all():
    """With answers to every move of the leader, a step's margin is the sum over its labelled rows,
    each row's label compared within that row; a step with no label adds nothing but its TD loss."""

    import torch

    from formation.recipe.loss import WEIGHTS, large_margin

    q = torch.randn(3, 16, generator=torch.Generator().manual_seed(0))
    labels = torch.tensor([[1, 0, -1, 3], [-1, -1, -1, -1], [-1, 2, -1, -1]])
    batch = {"actions": torch.tensor([5, 0, 6]), "n_step_returns": torch.zeros(3), "n_step_discounts": torch.zeros(3),
             "teacher_labels": labels, WEIGHTS: torch.ones(3)}
    loss, priority = margin_loss("follower", q, batch, margin=2.0, margin_gap=5.0)
    rows = q.view(3, 4, 4)
    first = sum(large_margin(rows[0, r].unsqueeze(0), torch.tensor([labels[0, r]]), 5.0) for r in (0, 1, 3))
    third = large_margin(rows[2, 1].unsqueeze(0), torch.tensor([2]), 5.0)
    td = torch.nn.functional.smooth_l1_loss(q.gather(1, batch["actions"].unsqueeze(1)).squeeze(1), torch.zeros(3))
    torch.testing.assert_close(loss, td + 2.0 * (first + third).squeeze() / 2)
    # priorities: the TD error plus the weighted margin, the unlabelled step its TD error alone
    td_abs = q.gather(1, batch["actions"].unsqueeze(1)).squeeze(1).abs()
    expected = td_abs + 2.0 * torch.stack([first.squeeze(), torch.tensor(0.0), third.squeeze()])
    np.testing.assert_allclose(priority, expected.numpy(), rtol=1e-5)


def test_threaded_module_updates_equal_rllibs_serial_update(monkeypatch):
    """On a CPU the learner updates its modules in parallel threads, the screens prepared once for both;
    the weights after an update must be those of RLlib's serial update on the same batch."""
    import torch
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    from formation.recipe.config import RunConfig
    from formation.recipe.qnet import DuelingQNetwork
    from formation.recipe.team import module_of_agent, spaces_of
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load("configs/smoke.yaml")
    config = build_algorithm_config(run)
    spaces = {m: spaces_of(run) for m in set(module_of_agent(run))}
    n = 16
    sample = random_sample(np.random.default_rng(0), n, spaces["leader"][0].shape, agents=2)
    weights, prepared = {}, {}
    real_prepare = DuelingQNetwork.prepare

    def counted_prepare(net, obs):
        prepared[threaded] += 1
        return real_prepare(net, obs)

    monkeypatch.setattr(DuelingQNetwork, "prepare", counted_prepare)
    for threaded in (True, False):
        prepared[threaded] = 0
        torch.manual_seed(0)
        learner = config.build_learner(spaces=spaces)
        learner.module_threads = threaded
        learner.set_replays([], module_of_agent(run))
        batch = MultiAgentBatch({m: SampleBatch(b) for m, b in module_batches(sample, module_of_agent(run)).items()},
                                env_steps=n)
        learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
        assert (learner._threads is not None) == threaded  # the path under test was taken
        weights[threaded] = {m: {k: v.clone() for k, v in learner.module[m].state_dict().items()}
                             for m in ("leader", "follower")}
    torch.manual_seed(0)
    before = config.build_learner(spaces=spaces)
    for m in ("leader", "follower"):
        for key, value in weights[True][m].items():
            torch.testing.assert_close(value, weights[False][m][key])
        moved = [k for k, v in weights[True][m].items() if not torch.equal(v, before.module[m].state_dict()[k])]
        assert any("q_network" in k for k in moved), m  # the update did change the weights
    # the layers without weights read the observations and the next ones once for both modules on the
    # threaded path; RLlib's serial path runs each module's own: once per module and kind of observation
    assert prepared == {True: 2, False: 4}


def test_the_rllib_learner_trains_the_shared_follower_network_on_each_rows_role():
    """Three followers share one RLlib module; a learner update reads each row's role, so every role's one-hot
    weights move, and the module's loss is the recipe's on that role's Q-values."""
    import torch
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    from formation.recipe.config import RunConfig
    from formation.recipe.learn import forward
    from formation.recipe.loss import dqn_loss
    from formation.recipe.team import module_of_agent, spaces_of
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load("configs/smoke.yaml", {"game.n_followers": 3})
    config = build_algorithm_config(run)
    spaces = {m: spaces_of(run) for m in set(module_of_agent(run))}
    n = 8
    sample = random_sample(np.random.default_rng(1), n, spaces["leader"][0].shape, agents=4, labelled=False)
    torch.manual_seed(0)
    learner = config.build_learner(spaces=spaces)
    learner.set_replays([], module_of_agent(run))
    module = learner.module["follower"]
    assert module.q_network.roles == 3
    batches = module_batches(sample, module_of_agent(run))
    follower = {k: torch.from_numpy(np.asarray(v)) for k, v in batches["follower"].items()}
    out = forward(module.q_network, module._target_q_network, follower["obs"], follower["new_obs"],
                  role=follower[ROLE])
    expected = dqn_loss(follower, out["q"], out["q_next"], out["q_target_next"], 0.0, 0.0)[0]
    fwd = module.forward_train(follower)
    settings = learner.config.get_config_for_module("follower")
    loss = learner.compute_loss_for_module(module_id="follower", config=settings, batch=follower, fwd_out=fwd)
    torch.testing.assert_close(loss, expected)
    before = module.q_network.advantage_role.weight.detach().clone()
    learner.update(batch=MultiAgentBatch({m: SampleBatch(b) for m, b in batches.items()}, env_steps=n),
                   timesteps={"num_env_steps_sampled_lifetime": 0})
    after = module.q_network.advantage_role.weight.detach()
    assert all(not torch.equal(before[:, r], after[:, r]) for r in range(3))  # every role was trained


def test_a_safety_head_adds_its_loss_but_not_its_wrong_verdicts_to_the_priority():
    import torch

    from formation.recipe.loss import SAFE, WEIGHTS
    from formation.rllib.module import SAFETY_LOGITS

    q = torch.zeros(2, 4)
    safe = torch.zeros(2, 16, dtype=torch.bool)
    safe[0, :3] = True  # three moves safe in the first state, none in the second
    logits = torch.full((2, 16), -2.0)
    logits[0, :5] = 2.0  # the head judges moves 3 and 4 of the first state safe too: two wrong verdicts
    batch = {"actions": torch.tensor([0, 1]), "n_step_returns": torch.tensor([1.0, -0.5]),
             "n_step_discounts": torch.zeros(2), "teacher_labels": torch.tensor([-1, -1]), SAFE: safe,
             WEIGHTS: torch.ones(2)}

    def loss_and_priority():
        from formation.rllib.learner import FormationLearner

        fwd = {"qf_preds": q, "qf_next_preds": torch.zeros(2, 4), "qf_target_next_preds": torch.zeros(2, 4),
               SAFETY_LOGITS: logits}
        learner = FormationLearner.__new__(FormationLearner)
        learner._priority, learner._stats = {}, {}
        config = SimpleNamespace(loss_weights={"margin": 0.0, "margin_gap": 5.0, "safety_weight": 1.0})
        loss = learner.compute_loss_for_module(module_id="leader", config=config, batch=batch, fwd_out=fwd)
        return loss, learner._priority["leader"], learner._stats["leader"]

    loss, priority, stats = loss_and_priority()
    td = torch.nn.functional.smooth_l1_loss(torch.zeros(2), torch.tensor([1.0, -0.5]))
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, safe.float())
    torch.testing.assert_close(loss, td + bce)
    np.testing.assert_allclose(priority, [1.0, 0.5])  # the TD errors alone
    assert stats["safety_error"] == 2 / 32


@pytest.mark.parametrize("finite", [True, False])
def test_one_finiteness_check_of_all_gradients_applies_them_as_rllib_does(finite):
    """The learner checks all gradients for nan and inf at once; the weights after an update must be those
    RLlib's per-tensor checks give, with finite gradients and with a nan among them (set to 0 by RLlib)."""
    import torch
    from ray.rllib.core.learner.torch.torch_learner import TorchLearner
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    from formation.recipe.config import RunConfig
    from formation.recipe.team import module_of_agent, spaces_of
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load("configs/smoke.yaml")
    config = build_algorithm_config(run)
    spaces = {m: spaces_of(run) for m in set(module_of_agent(run))}
    rng = np.random.default_rng(1)
    n, shape = 16, spaces["leader"][0].shape
    returns = rng.normal(size=(n, 2)).astype(np.float32)
    if not finite:
        returns[3, 0] = np.nan  # the leader's loss and gradients: nan
    sample = {"obs": rng.integers(0, 2, (n, *shape), dtype=np.uint8),
              "next_obs": rng.integers(0, 2, (n, *shape), dtype=np.uint8),
              "actions": rng.integers(0, 4, (n, 2)), "returns": returns,
              "discounts": np.full(n, 0.9, np.float32), "labels": rng.integers(-1, 4, (n, 2)),
              "weights": np.ones(n, np.float32)}
    weights = {}
    for name, apply in (("one check", None), ("rllib", TorchLearner.apply_gradients)):
        torch.manual_seed(0)
        learner = config.build_learner(spaces=spaces)
        learner.module_threads = False
        if apply is not None:
            learner.apply_gradients = apply.__get__(learner)
        learner.set_replays([], module_of_agent(run))
        batch = MultiAgentBatch({m: SampleBatch(b) for m, b in module_batches(sample, module_of_agent(run)).items()},
                                env_steps=n)
        learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
        weights[name] = {m: {k: v.clone() for k, v in learner.module[m].state_dict().items()}
                         for m in ("leader", "follower")}
    torch.manual_seed(0)
    before = config.build_learner(spaces=spaces)
    for m in ("leader", "follower"):
        for key, value in weights["one check"][m].items():
            torch.testing.assert_close(value, weights["rllib"][m][key])
            assert torch.isfinite(value).all()
        moved = [k for k, v in weights["one check"][m].items() if not torch.equal(v, before.module[m].state_dict()[k])]
        assert any("q_network" in k for k in moved), m  # the update did change the weights


def test_the_learner_updates_alike_on_a_batch_of_cells_and_on_the_screens_they_come_from():
    """The replay keeps only the cells of the screens where the networks read them per cell: the learner's
    update on such a batch (split per module, prepared once for both, forward, backward, step) must leave the
    same weights and give the same priorities as on the same batch of whole screens. No Ray cluster."""
    import torch

    from formation.recipe.config import RunConfig
    from formation.recipe.qnet import ScreenCells
    from formation.recipe.replay import FrameReplay
    from formation.recipe.rollout import GameRollout
    from formation.recipe.team import answers_leader, module_of_agent, reads_cells, replay_frame_shape, spaces_of
    from formation.rllib.algorithm import build_algorithm_config

    run = RunConfig.load("configs/smoke.yaml", {"game.obs_type": "pixels", "teacher.safety_horizon": 4})
    assert reads_cells(run) and run.train.prioritized
    board, k = (run.game.height, run.game.width), run.game.frame_stack
    # the same games into a replay of cells and one of whole screens: equal draws, equal ids
    samples = {}
    for cells in (True, False):
        rollout, rng = GameRollout(run.game, 8, seed=1, screen_cells=cells), np.random.default_rng(1)
        shape = replay_frame_shape(run) if cells else rollout.observer.frame_shape
        replay = FrameReplay(1000, shape, 2, k, seed=0)
        for _ in range(30):
            chunk = rollout.step(rng.integers(0, 4, (8, 2)), safe=rng.integers(0, 1 << 16, 8))
            replay.add(chunk)
        samples[cells] = replay.sample(16, n_step=run.train.n_step, gamma=run.train.gamma)
    np.testing.assert_array_equal(samples[True]["ids"], samples[False]["ids"])
    assert samples[True]["obs"].shape == (16, *board, 3 * k) and samples[False]["obs"].shape == (16, 84, 84, 3 * k)
    reader = ScreenCells((84, 84, 3 * k), board)
    for key in ("obs", "next_obs"):
        np.testing.assert_array_equal(samples[True][key], reader(torch.from_numpy(samples[False][key])).numpy())

    config = build_algorithm_config(run)
    agents = module_of_agent(run)
    spaces = {m: spaces_of(run) for m in set(agents)}
    weights, priorities = {}, {}
    for cells in (True, False, None):  # None: the weights before the update
        torch.manual_seed(0)
        learner = config.build_learner(spaces=spaces)
        learner.set_replays([], agents, [m for m in set(agents) if answers_leader(run, m)], safety=True)
        if cells is not None:
            priorities[cells] = learner.update_on(dict(samples[cells]))
        weights[cells] = {m: {key: value.clone() for key, value in learner.module[m].state_dict().items()}
                          for m in set(agents)}
    np.testing.assert_array_equal(priorities[True], priorities[False])
    for m in weights[True]:
        for key, value in weights[True][m].items():
            assert torch.equal(value, weights[False][m][key]), (m, key)
        assert any(not torch.equal(value, weights[None][m][key]) for key, value in weights[True][m].items()), m
