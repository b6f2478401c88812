"""A safety head learnt beside the Q-values (``teacher.safety_horizon``): the planner labels every visited
state with the joint moves that start safe steps, the labels travel through the replay
to the learner, which fits the head, and greedy play keeps to the joint moves the head judges safe."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame, Observer
from formation.planner import surviving_first_moves_many
from formation.policy import Policy, export, greedy_within, load
from formation.recipe.config import RunConfig
from formation.recipe.loss import SAFE, module_batches
from formation.recipe.qnet import NetworkSpec, outputs_of
from formation.recipe.replay import FrameReplay
from formation.recipe.rollout import GameRollout, concatenate

SMOKE = "configs/smoke.yaml"


@pytest.mark.parametrize("key,value,message", [
    ("teacher.safety_horizon", -1, "teacher.safety_horizon: -1 is not allowed; allowed: an integer >= 0"),
    ("teacher.safety_horizon", "path", "teacher.safety_horizon: 'path' is not allowed; allowed: an integer >= 0"),
    ("teacher.safety_weight", -0.5, "teacher.safety_weight: -0.5 is not allowed; allowed: a number in [0.0, inf]"),
    ("teacher.safety_encoder", True, "teacher.safety_encoder: true needs teacher.safety_horizon other than 0; "
                                   "allowed: false"),
    ("teacher.safety_encoder", "own", "teacher.safety_encoder: 'own' is not allowed; allowed: true, false"),
])
def test_a_bad_safety_setting_is_one_line(key, value, message):
    with pytest.raises(ConfigError) as err:
        RunConfig.load(SMOKE, {key: value})
    assert str(err.value) == message


def test_a_safety_head_needs_one_follower():
    with pytest.raises(ConfigError, match=r"teacher.safety_horizon: 2 needs game.n_followers: 1 \(not 2\)"):
        RunConfig.load(SMOKE, {"teacher.safety_horizon": 2, "game.n_followers": 2, "game.width": 12,
                               "train.follower_answers_leader": False})


def test_the_head_gives_16_logits_beside_unchanged_q_values():
    torch.manual_seed(0)
    plain = NetworkSpec((9, 9, 8), high=1.0, hidden=32, channels=(4, 8, 8), answers_leader=True).build()
    torch.manual_seed(0)
    headed = NetworkSpec((9, 9, 8), high=1.0, hidden=32, channels=(4, 8, 8), answers_leader=True, safety=True).build()
    obs = torch.randint(0, 2, (5, 9, 9, 8), dtype=torch.uint8)
    assert plain.safety is None
    assert torch.equal(plain(obs), headed(obs))  # the head adds weights after the Q-values' own
    assert headed.safety_logits(headed.prepare(obs)).shape == (5, 16)


def test_a_head_with_an_encoder_of_its_own_leaves_the_q_values_and_their_layers_alone():
    torch.manual_seed(0)
    shared = NetworkSpec((9, 9, 8), high=1.0, hidden=32, channels=(4, 8, 8), safety=True).build()
    torch.manual_seed(0)
    own = NetworkSpec((9, 9, 8), high=1.0, hidden=32, channels=(4, 8, 8), safety=True, safety_encoder=True).build()
    assert shared.safety_encoder is None and own.safety_encoder is not None
    obs = torch.randint(0, 2, (5, 9, 9, 8), dtype=torch.uint8)
    assert torch.equal(shared(obs), own(obs))  # its encoder adds weights after the Q-values' own
    x = own.prepare(obs)
    logits = own.safety_logits(x)
    assert torch.equal(logits, own.safety_logits(x, own.features(x))) and logits.shape == (5, 16)
    assert not torch.equal(logits, shared.safety_logits(x))  # the same head on other features
    assert torch.equal(shared.safety_logits(x, shared.features(x)), shared.safety_logits(x))
    q, safe = outputs_of({"leader": own}, obs)
    assert torch.equal(q["leader"], own(obs)) and torch.allclose(safe.reshape(5, 16), torch.sigmoid(logits))
    # the safety loss reaches the head's encoder and not the Q-values' layers; with shared features it does
    for net in (shared, own):
        net.zero_grad()
        net.safety_logits(x).square().mean().backward()
    assert shared.encoder[0].weight.grad.abs().sum() > 0
    assert own.encoder[0].weight.grad is None
    assert own.safety_encoder[0][0].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="safety_encoder: needs a safety head"):
        NetworkSpec((9, 9, 8), high=1.0, safety_encoder=True).build()


def test_training_and_exports_build_the_head_with_its_encoder(tmp_path):
    from formation.recipe.team import module_of_agent, network_specs
    from formation.rllib.algorithm import module_specs

    run = RunConfig.load(SMOKE, {"teacher.safety_horizon": 2, "teacher.safety_encoder": True})
    specs, agent_modules = network_specs(run), module_of_agent(run)
    for module, spec in module_specs(run).items():
        trained = spec.build().q_network
        assert trained.safety_encoder is not None and specs[module].safety_encoder
        assert trained.state_dict().keys() == specs[module].build().state_dict().keys()
    networks = {m: s.build() for m, s in specs.items()}
    policy = Policy(run.game, networks, specs, agent_modules, "test")
    reloaded = load(export(policy, tmp_path / "export"))
    card = json.loads((tmp_path / "export" / "policy.json").read_text())
    assert all(card["networks"][m]["safety_encoder"] is True for m in specs)
    game = BatchedGame(run.game, batch_size=8, seed=0)
    game.reset()
    obs = Observer(game).observe(np.ones(8, bool))
    assert all(net.safety_encoder is not None for net in reloaded.networks.values())
    assert (reloaded.learned_safe_moves(obs) == policy.learned_safe_moves(obs)).all()


def visited_states(config: GameConfig, games: int = 8, steps: int = 6, seed: int = 3):
    """Chunks of a rollout with the safe joint moves of each state, as the rollout actor records them."""
    rollout = GameRollout(config, games, seed=seed)
    rng = np.random.default_rng(seed)
    chunks, states = [], []
    for _ in range(steps):
        scenarios = [rollout.game.scenario(i) for i in range(games)]
        safe = surviving_first_moves_many(scenarios, config=config, horizon=2)
        states.append((scenarios, safe))
        chunks.append(rollout.step(rng.choice([0, 3], size=(games, 2)), safe=safe))
    return concatenate(chunks), states


def test_safe_moves_travel_through_the_replay_to_the_module_batches():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2, height=9, width=9, n_obstacles=2)
    chunk, states = visited_states(config)
    recorded = np.concatenate([safe for _, safe in states])
    assert (chunk.safe == recorded).all() and (recorded != 0).any() and (recorded != 0xFFFF).any()
    replay = FrameReplay(1000, chunk.frames.shape[1:], 2, 2, seed=0)
    replay.add(chunk)
    sample = replay.sample(32, n_step=1, gamma=0.9)
    slots = sample["ids"] % replay.capacity
    assert (sample["safe"] == replay.safe[slots]).all()
    batches = module_batches(sample, ["leader", "follower"], frozenset({"follower"}), safety=True)
    for module in ("leader", "follower"):
        bits = batches[module][SAFE]
        assert bits.shape == (32, 16)
        assert (np.packbits(bits[:, ::-1], axis=1, bitorder="big").view(">u2")[:, 0] == sample["safe"]).all()
    assert SAFE not in module_batches(sample, ["leader", "follower"], frozenset({"follower"}))["leader"]


def test_greedy_play_keeps_to_the_moves_the_head_judges_safe(tmp_path):
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2, height=9, width=9, n_obstacles=2)
    spec = NetworkSpec(obs_shape=(9, 9, 8), high=1.0, hidden=16, channels=(4, 8, 8), safety=True)
    follower_spec = NetworkSpec(**{**spec.__dict__, "answers_leader": True})
    torch.manual_seed(0)
    networks = {"leader": spec.build(), "follower": follower_spec.build()}
    with torch.no_grad():  # the head: every joint move safe but those where the leader goes forward
        for net in networks.values():
            net.safety[-1].weight.zero_()
            net.safety[-1].bias.copy_(torch.tensor([-9.0] * 4 + [9.0] * 12))
            net.advantage[-1].bias[0] += 100.0  # and the networks' greedy leader move is forward
    policy = Policy(config, networks, {"leader": spec, "follower": follower_spec}, ["leader", "follower"], "test")
    game = BatchedGame(config, batch_size=16, seed=0)
    game.reset()
    obs = Observer(game).observe(np.ones(16, bool))
    assert policy.learned_veto
    assert (policy.without_learned_veto().act_batch(obs)[:, 0] == 0).all()
    assert (policy.act_batch(obs)[:, 0] != 0).all()
    # the moves with the Q-values they came from (as the refit plays): one pass of each network
    moves, by_module = policy.act_batch_and_q(obs)
    assert (moves == policy.act_batch(obs)).all()
    assert all(np.array_equal(by_module[m], q) for m, q in policy.outputs(obs)[0].items())
    assert sorted(by_module) == ["follower", "leader"]
    # the head travels with an export, and so does the veto
    reloaded = load(export(policy, tmp_path / "export"))
    assert json.loads((tmp_path / "export" / "policy.json").read_text())["networks"]["leader"]["safety"] is True
    assert (reloaded.act_batch(obs) == policy.act_batch(obs)).all()


def test_without_heads_nothing_is_vetoed_and_greedy_within_all_moves_is_plain_greedy():
    config = GameConfig.from_setting(2, obs_type="grid", frame_stack=2, height=9, width=9, n_obstacles=2)
    spec = NetworkSpec(obs_shape=(9, 9, 8), high=1.0, hidden=16, channels=(4, 8, 8))
    follower_spec = NetworkSpec(**{**spec.__dict__, "answers_leader": True})
    torch.manual_seed(1)
    networks = {"leader": spec.build(), "follower": follower_spec.build()}
    policy = Policy(config, networks, {"leader": spec, "follower": follower_spec}, ["leader", "follower"], "test")
    game = BatchedGame(config, batch_size=32, seed=1)
    game.reset()
    obs = Observer(game).observe(np.ones(32, bool))
    assert not policy.learned_veto and policy.learned_safe_moves(obs) is None
    by_module, safe_probability = policy.outputs(obs)
    assert safe_probability is None
    assert (greedy_within(by_module, policy.agent_modules, None, None) == policy.act_batch(obs)).all()
    moves, q = policy.act_batch_and_q(obs)
    assert (moves == policy.act_batch(obs)).all() and (moves == policy.q_batch(obs).argmax(-1)).all()
    assert sorted(q) == sorted(by_module) and all(np.array_equal(q[m], by_module[m]) for m in q)
