"""The DQN arithmetic against hand computations, and the network's input handling."""

import numpy as np
import pytest
import torch

from formation.config import ConfigError
from formation.recipe.loss import double_q_target, large_margin, large_margin_sets
from formation.recipe.qnet import DuelingQNetwork, LeaderWindow, NetworkSpec, dueling


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


def test_large_margin_towards_a_set_compares_with_the_best_accepted_action():
    q = torch.tensor([[1.0, 2.0, 3.0, 0.0], [1.0, 2.0, 3.0, 0.0], [1.0, 2.0, 3.0, 0.0]])
    accepted = torch.tensor([[True, True, False, False], [False, True, True, False], [False, False, True, False]])
    # row 1: action 2 (3, not accepted) plus the gap 5 against the best accepted (2): 6; row 2: the best
    # accepted (3) leads action 0 (1) by 2, less than the gap: 5 - 2 = 3 remains; row 3: one accepted (3),
    # action 1 (2) plus the gap: 4
    assert torch.allclose(large_margin_sets(q, accepted, 5.0), torch.tensor([6.0, 3.0, 4.0]))
    # one accepted action: the margin towards a label
    assert torch.allclose(large_margin_sets(q, accepted[2:].expand(3, 4), 5.0),
                          large_margin(q, torch.tensor([2, 2, 2]), 5.0))
    # every action accepted: nothing to learn
    assert (large_margin_sets(q, torch.ones(3, 4, dtype=torch.bool), 5.0) == 0).all()


def test_network_takes_uint8_screens_and_grids():
    for shape, high in (((84, 84, 12), 255), ((25, 25, 8), 1)):
        net = NetworkSpec(shape, high).build()
        obs = torch.randint(0, high + 1, (5, *shape), dtype=torch.uint8)
        q = net(obs)
        assert q.shape == (5, 4) and q.dtype == torch.float32
        # normalisation: a screen scaled to the other range gives other values
        assert not torch.allclose(net(obs), net(obs // 2))


def test_leader_window_moves_the_leader_to_a_fixed_place_on_grids():
    # one frame of the grid planes (destination, obstacles, followers, leader), stacked twice
    h, w = 7, 9
    frame = torch.zeros(2, h, w, 4, dtype=torch.uint8)
    frame[0, 0, 4, 0] = 1  # destination
    frame[0, 3, 4, 1] = 1  # an obstacle
    frame[0, 3, 6, 1] = 1  # another, outside the window
    frame[0, 5, 2, 3] = 1  # the leader at (5, 2) ...
    frame[0, 5, 0, 2] = 1  # ... its follower two columns left
    frame[1, 0, 0, 3] = 1  # the second game's leader in the top-left corner
    older = torch.zeros_like(frame)
    older[0, 6, 2, 3] = 1  # the leader one row lower in the older frame (it moved forward)
    obs = torch.cat([older, frame], dim=3)
    window = LeaderWindow((h, w, 8), (3, 1, 2), frame_channels=4, screens=False)
    crop = window(obs)
    assert crop.shape == (2, 3 + 1 + 1, 2 * 2 + 1, 9) == (2, *window.out_shape)
    up, side = 3, 2
    expected = torch.zeros(2, 5, 5, 9)
    expected[0, up, side, 7] = 1  # the leader, newest frame
    expected[0, up + 1, side, 3] = 1  # the leader in the older frame, one row below
    expected[0, up, side - 2, 6] = 1  # the follower
    expected[0, up - 2, side + 2, 5] = 1  # the obstacle at (3, 4): 2 rows up, 2 columns right
    expected[0, :, :, 8] = 1  # rows 2..6 and columns 0..4 of the board are all on it
    expected[1, up:, side:, 8] = 1  # the corner: only the lower right quarter is board
    expected[1, up, side, 7] = 1
    assert torch.equal(crop, expected)  # the destination (0, 4) is 5 rows up: outside


def test_the_compass_marks_the_destination_or_the_window_edge_nearest_to_it():
    h, w = 9, 11
    obs = torch.zeros(3, h, w, 4, dtype=torch.uint8)
    obs[:, 0, 5, 0] = 1  # the destination, at (0, 5), in every game
    obs[0, 8, 1, 3] = 1  # a leader 8 rows below and 4 columns left of it: outside a (3, 1, 2) window
    obs[1, 2, 6, 3] = 1  # a leader 2 rows below and 1 column right: inside
    obs[2, 8, 1, 3] = 1
    obs[2, 0, 5, 0] = 0  # hidden (an agent on it): nothing marked
    window = LeaderWindow((h, w, 4), (3, 1, 2), frame_channels=4, screens=False, compass=True)
    crop = window(obs)
    assert crop.shape == (3, 5, 5, 6) == (3, *window.out_shape)
    compass = crop[..., 4]
    expected = torch.zeros(3, 5, 5)
    expected[0, 0, 4] = 1  # up and right, beyond both edges: the top-right corner
    expected[1, 1, 1] = 1  # the destination itself: 2 rows up, 1 column left of the leader at (3, 2)
    assert torch.equal(compass, expected)
    assert torch.equal(crop[1, 1, 1, 0], torch.tensor(1.0))  # where the destination's own plane shows it
    # the board plane stays last, and the compass changes no other plane
    plain = LeaderWindow((h, w, 4), (3, 1, 2), frame_channels=4, screens=False)(obs)
    assert torch.equal(crop[..., :4], plain[..., :4]) and torch.equal(crop[..., 5], plain[..., 4])


def test_the_compass_points_at_the_destination_on_screens_read_per_cell():
    from formation.config import GameConfig
    from formation.game import BatchedGame, Observer
    from formation.recipe.config import RunConfig
    from formation.recipe.team import network_specs

    run = RunConfig.from_dict({"game": {"setting": 3, "obs_type": "pixels", "frame_stack": 2},
                               "train": {"destination_compass": True}})
    spec = network_specs(run)["leader"]
    assert spec.compass and spec.window == (12, 3, 10)
    assert NetworkSpec.from_dict(spec.to_dict()) == spec  # as a card keeps it
    game = BatchedGame(GameConfig.from_setting(3, obs_type="pixels", frame_stack=2), 2, seed=1)
    game.reset()
    obs = torch.from_numpy(Observer(game).observe(np.ones(2, dtype=bool)).copy())
    net = spec.build()
    plain = network_specs(RunConfig.from_dict({"game": run.game.to_dict()}))["leader"].build()
    x, without = net.prepare(obs), plain.prepare(obs)  # (N, C, rows, columns), the compass the plane before the board's
    assert x.shape[1] == without.shape[1] + 1 and x.shape[2:] == (16, 21)
    # the leaders start 47 rows below the destination and 10 columns left of it (at the window's edge): the top
    # row's last entry
    leader = game.positions[:, 0]
    assert (leader[:, 1] == 15).all() and (leader[:, 0] > 12).all()
    assert torch.equal(x[:, -2].nonzero(), torch.tensor([[0, 0, 20], [1, 0, 20]]))
    assert torch.equal(x[:, :-2], without[:, :-1]) and torch.equal(x[:, -1], without[:, -1])
    assert net(obs).shape == (2, 4)


def test_leader_window_finds_the_leader_on_rendered_screens():
    from formation.config import GameConfig
    from formation.game import BatchedGame, Observer
    from formation.recipe.config import RunConfig
    from formation.recipe.team import network_specs

    run = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "pixels", "frame_stack": 2},
                               "train": {"leader_window": [2, 1, 3], "screen_cells": False,
                                         "obstacle_forecast": False}})
    spec = network_specs(run)["leader"]
    # 3.36 pixels a cell: 2 cells above, 1 below and 3 either side, plus the leader's own cell
    assert (spec.obs_shape, spec.window, spec.frame_channels, spec.cells) == ((84, 84, 6), (7, 7, 14), 3, None)
    game = BatchedGame(GameConfig.from_setting(1, obs_type="pixels", frame_stack=2), 4, seed=3)
    game.reset()
    obs = torch.from_numpy(Observer(game).observe(torch.ones(4, dtype=torch.bool).numpy()).copy())
    net = spec.build()
    crop = net.window(obs)
    up, side = spec.window[0], spec.window[2]
    # every game's window has the leader's blue top-left pixel at (up, side), the block's top-left
    assert torch.equal(crop[:, up, side, 3:6], torch.tensor([[0.0, 0.0, 255.0]] * 4))
    assert torch.equal(crop[:, up - 1, side, 3:6], torch.zeros(4, 3))
    assert torch.equal(crop[:, up, side - 1, 3:6], torch.zeros(4, 3))
    assert net(obs).shape == (4, 4)


def _colours_of_grid(grid):
    """The screen's colour of every cell from the grid planes, drawn in the screen's order."""
    from formation.game.render import BLUE, GREEN, RED, WHITE
    out = torch.zeros(*grid.shape[:-1], 3, dtype=torch.uint8)
    for plane, colour in enumerate((WHITE, RED, GREEN, BLUE)):
        out[torch.from_numpy(grid[..., plane] > 0)] = torch.tensor(colour, dtype=torch.uint8)
    return out


def test_screen_cells_reads_every_cell_of_rendered_screens_without_loss():
    import numpy as np

    from formation.config import GameConfig
    from formation.game import BatchedGame
    from formation.game.render import GridRenderer, ScreenRenderer
    from formation.recipe.qnet import ScreenCells

    for setting in (1, 3):  # 3.36 and 1.68 pixels a cell
        cfg = GameConfig.from_setting(setting)
        game = BatchedGame(cfg, 6, seed=setting)
        game.reset()
        screens, grids = ScreenRenderer(game), GridRenderer(game)
        reader = ScreenCells((84, 84, 3), (cfg.height, cfg.width))
        actions = np.random.default_rng(0)
        for _ in range(4):
            cells = reader(torch.from_numpy(screens.render().copy()))
            assert cells.shape == (6, cfg.height, cfg.width, 3) and cells.dtype == torch.uint8
            assert torch.equal(cells, _colours_of_grid(grids.render()))
            game.step(actions.integers(0, 4, (6, game.n_agents)))


def test_a_screen_read_per_cell_has_its_window_in_cells_with_the_leader_at_the_fixed_place():
    from formation.config import GameConfig
    from formation.game import BatchedGame, Observer
    from formation.recipe.config import RunConfig
    from formation.recipe.team import network_specs

    run = RunConfig.from_dict({"game": {"setting": 3, "obs_type": "pixels", "frame_stack": 2},
                               "train": {"leader_window": [2, 1, 3], "screen_cells": True}})
    spec = network_specs(run)["leader"]
    assert (spec.window, spec.frame_channels, spec.cells, spec.forecast) == ((2, 1, 3), 3, (50, 50), True)
    assert spec.build().cells.out_shape == (50, 50, 6)
    game = BatchedGame(GameConfig.from_setting(3, obs_type="pixels", frame_stack=2), 4, seed=5)
    game.reset()
    obs = torch.from_numpy(Observer(game).observe(torch.ones(4, dtype=torch.bool).numpy()).copy())
    net = NetworkSpec((84, 84, 6), 255, window=(2, 1, 3), frame_channels=3, cells=(50, 50)).build()
    crop = net.window(net.cells(obs))
    assert crop.shape == (4, 2 + 1 + 1, 2 * 3 + 1, 7)
    # one entry per cell: the leader's cell at (2, 3)
    assert torch.equal(crop[:, 2, 3, 3:6], torch.tensor([[0.0, 0.0, 255.0]] * 4))
    leader = torch.from_numpy(game.positions[:, 0])
    # the window's cell (i, j) is the board's cell (leader row - 2 + i, leader column - 3 + j)
    board = net.cells(obs)[..., 3:6]
    for g in range(4):
        r, c = int(leader[g, 0]), int(leader[g, 1])
        for i in range(4):
            for j in range(7):
                rr, cc = r - 2 + i, c - 3 + j
                inside = 0 <= rr < 50 and 0 <= cc < 50
                assert crop[g, i, j, 6] == float(inside)
                if inside:
                    assert torch.equal(crop[g, i, j, 3:6], board[g, rr, cc].float())
    assert net(obs).shape == (4, 4)
    # without a window the network reads the whole board, one entry per cell
    whole = NetworkSpec((84, 84, 6), 255, cells=(50, 50)).build()
    assert whole.cells(obs).shape == (4, 50, 50, 6) and whole(obs).shape == (4, 4)


def test_a_follower_that_answers_the_leader_reads_the_row_of_the_leaders_move():
    from formation.recipe.qnet import team_q_values

    rng = np.random.default_rng(0)
    leader, follower = rng.normal(size=(5, 4)), rng.normal(size=(5, 16))
    plain = rng.normal(size=(5, 4))
    q = {"leader": leader, "follower": follower, "plain": plain}
    team = team_q_values(q, ["leader", "follower", "plain"])
    assert team.shape == (5, 3, 4)
    np.testing.assert_array_equal(team[:, 0], leader)
    np.testing.assert_array_equal(team[:, 2], plain)  # a module of four Q-values reads them as they are
    for i in range(5):  # the row of the leader's greedy move
        np.testing.assert_array_equal(team[i, 1], follower[i].reshape(4, 4)[leader[i].argmax()])
    moves = np.array([3, 0, 1, 2, 3])
    played = team_q_values(q, ["leader", "follower"], leader_moves=moves)
    for i in range(5):  # or of the move the leader plays
        np.testing.assert_array_equal(played[i, 1], follower[i, 4 * moves[i]: 4 * moves[i] + 4])
    net = NetworkSpec((9, 9, 8), high=1.0, answers_leader=True).build()
    assert net(torch.zeros(2, 9, 9, 8, dtype=torch.uint8)).shape == (2, 16)


def test_a_network_the_followers_share_reads_each_ones_role_as_a_one_hot_input():
    """A network of three roles gives each role the Q-values of the same layers reading the features and the
    role's one-hot code side by side; each follower reads its own role's, and a loss reads the row's role."""
    from formation.recipe.learn import forward
    from formation.recipe.qnet import agent_roles, team_q_values

    torch.manual_seed(0)
    spec = NetworkSpec((9, 9, 8), high=1.0, hidden=16, channels=(4, 8, 8), answers_leader=True, roles=3)
    net = spec.build()
    obs = torch.randint(0, 2, (5, 9, 9, 8), dtype=torch.uint8)
    q = net(obs)
    assert q.shape == (5, 3, 16)
    features = net.features(net.prepare(obs))
    for role in range(3):  # by hand: the first layers read [features, one-hot role]
        code = torch.nn.functional.one_hot(torch.full((5,), role), 3).float()
        both = torch.cat([features, code], dim=1)

        def head(layers, role_layer, inputs):
            weight = torch.cat([layers[0].weight, role_layer.weight], dim=1)
            return layers[2](torch.relu(inputs @ weight.T + layers[0].bias))

        torch.testing.assert_close(q[:, role], dueling(head(net.value, net.value_role, both),
                                                       head(net.advantage, net.advantage_role, both)))
    assert not torch.allclose(q[:, 0], q[:, 1])  # the roles differ on the same screens
    modules = ["leader", "follower", "follower", "follower"]
    assert agent_roles(modules) == [0, 0, 1, 2]
    leader = torch.randn(5, 4).numpy()
    team = team_q_values({"leader": leader, "follower": q.detach().numpy()}, modules)
    for agent, role in ((1, 0), (2, 1), (3, 2)):
        rows = q[:, role].detach().numpy().reshape(5, 4, 4)[np.arange(5), leader.argmax(1)]
        np.testing.assert_array_equal(team[:, agent], rows)
    role = torch.tensor([2, 0, 1, 1, 0])
    out = forward(net, net, obs, obs, role=role)
    torch.testing.assert_close(out["q"], q[torch.arange(5), role])
    torch.testing.assert_close(out["q_target_next"], q[torch.arange(5), role].detach())
    assert NetworkSpec.from_dict(spec.to_dict()) == spec
    with pytest.raises(ValueError, match="roles"):
        NetworkSpec((9, 9, 8), high=1.0, safety=True, roles=2).build()


def test_networks_that_prepare_alike_share_one_preparation_and_keep_their_q_values(monkeypatch):
    from formation.recipe.qnet import q_values_of

    torch.manual_seed(0)
    shape = (84, 84, 12)
    reading = {"cells": (25, 25), "forecast": True, "frame_channels": 3}
    leader = NetworkSpec(shape, window=(12, 3, 10), **reading).build()
    follower = NetworkSpec(shape, window=(12, 3, 10), answers_leader=True, **reading).build()
    wider = NetworkSpec(shape, window=(12, 3, 12), **reading).build()
    assert leader.prepare_key == follower.prepare_key != wider.prepare_key
    obs = torch.randint(0, 256, (3, *shape), dtype=torch.uint8)
    calls = []
    real = DuelingQNetwork.prepare
    monkeypatch.setattr(DuelingQNetwork, "prepare", lambda net, o: calls.append(net) or real(net, o))
    q = q_values_of({"leader": leader, "follower": follower, "wider": wider}, obs)
    assert calls == [leader, wider]  # the follower reads the leader's preparation
    for name, net in (("leader", leader), ("follower", follower), ("wider", wider)):
        torch.testing.assert_close(q[name], net(obs))


def test_one_spec_builds_the_network_the_rllib_module_and_the_card():
    """``NetworkSpec`` is the one spelling of a network: training's RLlib module is built from it, the card
    stores it, and a card of 0.1 (with ``row_scan: 0``) reads back the same spec."""
    from formation.recipe.config import RunConfig
    from formation.recipe.team import network_specs
    from formation.rllib.algorithm import module_specs

    run = RunConfig.load("configs/smoke.yaml", {"teacher.safety_horizon": 2})
    specs = network_specs(run)
    for module, rl_spec in module_specs(run).items():
        built = rl_spec.build().q_network
        assert built.spec == specs[module]
        assert built.state_dict().keys() == specs[module].build().state_dict().keys()
        card = specs[module].to_dict()
        assert NetworkSpec.from_dict(card) == specs[module]
        assert NetworkSpec.from_dict({**card, "row_scan": 0}) == specs[module]
    with pytest.raises(ConfigError, match=r"^networks\.leader\.rows: unknown key; allowed: obs_shape, "):
        NetworkSpec.from_dict({**specs["leader"].to_dict(), "rows": 3}, "networks.leader")


@pytest.mark.parametrize("setting", [1, 3])
@pytest.mark.parametrize("safety_encoder", [False, True])
def test_networks_give_the_same_outputs_on_the_cells_the_replay_keeps_as_on_whole_screens(setting, safety_encoder):
    """The replay keeps only the cells of the screens; the learner's networks read those while acting reads
    whole screens. Every output (Q-values of the leader's and of the answering follower's network, safety
    logits, what the layers without weights prepare) must be the same floats from both."""
    from formation.recipe.config import RunConfig
    from formation.recipe.qnet import outputs_of
    from formation.recipe.replay import FrameReplay
    from formation.recipe.rollout import GameRollout
    from formation.recipe.team import network_specs, reads_cells, replay_frame_shape

    run = RunConfig.load(f"configs/setting{setting}.yaml",
                         {"teacher.safety_horizon": 8, "teacher.safety_encoder": safety_encoder})
    assert reads_cells(run)
    torch.manual_seed(setting)
    nets = {m: spec.build().eval() for m, spec in network_specs(run).items()}
    assert set(nets) == {"leader", "follower"} and nets["follower"].spec.answers_leader
    games, rng = 6, np.random.default_rng(setting)
    rollout = GameRollout(run.game, games, seed=setting, screen_cells=True)
    replay = FrameReplay(100, replay_frame_shape(run), 2, run.game.frame_stack)
    for _ in range(4):  # the obstacles move: the forecast reads their motion
        screens = torch.from_numpy(rollout.observations.copy())  # what the agents act on
        ids = replay.added + np.arange(games)  # the step's records, one per game
        replay.add(rollout.step(np.repeat(rng.integers(0, 4, (games, 1)), 2, axis=1)))
    cells, ok = replay.stack(ids)  # the last step's stacks, as the learner's batches bring them
    cells = torch.from_numpy(cells)
    board = (run.game.height, run.game.width)
    assert ok.all() and screens.shape == (games, 84, 84, 12) and cells.shape == (games, *board, 12)
    with torch.no_grad():
        for name, net in nets.items():
            assert net.cells(cells) is cells and torch.equal(net.cells(screens), cells)  # cells pass as they are
            x_screens, x_cells = net.prepare(screens), net.prepare(cells)
            assert torch.equal(x_screens, x_cells), name
            assert torch.equal(net(screens), net(cells)), name
            logits = net.safety_logits(x_screens), net.safety_logits(x_cells)
            assert logits[0].shape == (6, 16) and torch.equal(*logits), name
        (q_screens, safe_screens), (q_cells, safe_cells) = outputs_of(nets, screens), outputs_of(nets, cells)
    assert all(torch.equal(q_screens[m], q_cells[m]) for m in nets) and torch.equal(safe_screens, safe_cells)
    assert len({tuple(row.tolist()) for row in q_screens["leader"]}) > 1  # the states are told apart
