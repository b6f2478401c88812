"""The game seen in a mirror (formation.game.mirror) and ``train.mirror``, which learns from it: on settings
1-2 the mirror of a state plays out as the mirror of its play, on screen and in rewards, and the teacher's
labels of a mirrored state are the mirrored labels; the learner mirrors whole steps, nothing else."""

import itertools

import numpy as np
import pytest

import formation.env as fenv
from formation.config import ConfigError, GameConfig
from formation.game import BatchedGame
from formation.game.mirror import MIRRORED_MOVE, mirror_joint_masks, mirror_scenario, mirror_steps, mirror_symmetric
from formation.learn.config import RunConfig, TrainSettings
from formation.learn.teacher import Teacher


def test_mirrored_moves_swap_left_and_right():
    assert MIRRORED_MOVE.tolist() == [0, 2, 1, 3]  # F, FL -> FR, FR -> FL, S
    assert (MIRRORED_MOVE[MIRRORED_MOVE] == np.arange(4)).all()


@pytest.mark.parametrize("setting", [1, 2, 3, 4])
def test_settings_1_and_2_are_their_own_mirror_image_3_and_4_are_not(setting):
    for obs_type in ("pixels", "grid"):
        why = mirror_symmetric(GameConfig.from_setting(setting, obs_type=obs_type))
        if setting <= 2:
            assert why is None
        else:  # width 50: the destination (0, 25) is not the middle column
            assert "odd width" in why and "50" in why
    assert "one follower" in mirror_symmetric(GameConfig.from_setting(1, n_followers=2))


@pytest.mark.parametrize("setting,obs_type,frame_stack", [(1, "pixels", 4), (2, "pixels", 2), (1, "grid", 2)])
def test_a_mirrored_scenario_plays_out_as_the_mirror_of_its_play(setting, obs_type, frame_stack):
    config = GameConfig.from_setting(setting, obs_type=obs_type, frame_stack=frame_stack)
    rng = np.random.default_rng(setting)
    compared = 0
    for seed in range(10):
        env, mirrored = fenv.parallel_env(setting, obs_type=obs_type, frame_stack=frame_stack), \
            fenv.parallel_env(setting, obs_type=obs_type, frame_stack=frame_stack)
        obs, _ = env.reset(seed=seed)
        scenario = env.game.scenario(0)
        obs_m, _ = mirrored.reset(options={"scenario": mirror_scenario(scenario, config).to_dict()})
        for step in range(30):
            for agent in env.agents:
                assert (obs_m[agent] == obs[agent][:, ::-1]).all(), (seed, step, agent)
            compared += 1
            together = int(rng.integers(0, 4))  # mostly one move for all, so that the formation lasts
            moves = {agent: together if rng.random() < 0.8 else int(rng.integers(0, 4)) for agent in env.agents}
            obs, rewards, terminated, truncated, infos = env.step(moves)
            obs_m, rewards_m, terminated_m, truncated_m, infos_m = mirrored.step(
                {agent: int(MIRRORED_MOVE[move]) for agent, move in moves.items()})
            assert rewards_m == rewards and terminated_m == terminated and truncated_m == truncated
            for agent in infos:
                row, col = infos[agent]["position"]
                assert list(infos_m[agent]["position"]) == [row, config.width - 1 - col]
                for key in ("collided", "formation_kept", "distance", "reached"):
                    assert infos_m[agent][key] == infos[agent][key]
            if not env.agents:
                break
    assert compared >= 40


def test_teacher_labels_and_answers_of_a_mirrored_state_are_mirrored_off_the_middle_column():
    """The lockstep order ranks the move towards the destination's column first, so it is the same in a
    mirror except on the middle column (there: left first); the learner's mirrored labels are the
    teacher's own elsewhere."""
    config = GameConfig.from_setting(1)
    defaults = TrainSettings()
    teacher = Teacher(config, defaults.planner_slack, defaults.label_order, defaults.robust_first_step)
    game = BatchedGame(config, batch_size=1)
    compared = 0
    for seed in range(6):
        game.reset(seed=seed)
        while not game.done[0]:
            scenario, first = game.scenario(0), game.steps[0] == 0
            label = teacher.label(scenario, first_step=first)
            if label is None:
                break
            mirror = mirror_scenario(scenario, config)
            mirrored_label = teacher.label(mirror, first_step=first)
            if scenario.leader[1] != config.width // 2:
                assert mirrored_label == tuple(MIRRORED_MOVE[list(label)]), (seed, game.steps[0])
                for leader_move in range(4):
                    answer = teacher.answer(scenario, label, leader_move)
                    mirrored_answer = teacher.answer(mirror, mirrored_label, int(MIRRORED_MOVE[leader_move]))
                    assert mirrored_answer == (None if answer is None else tuple(MIRRORED_MOVE[list(answer)]))
                accepted = np.array([teacher.accepted(scenario, label, first)])
                assert teacher.accepted(mirror, mirrored_label, first) == mirror_joint_masks(accepted)[0]
                compared += 1
            game.step(np.array([label]))
    assert compared >= 100


def replay_sample(n=64, shape=(84, 84, 12), seed=0):
    rng = np.random.default_rng(seed)
    return {"obs": rng.integers(0, 256, (n, *shape), dtype=np.uint8),
            "next_obs": rng.integers(0, 256, (n, *shape), dtype=np.uint8),
            "actions": rng.integers(0, 4, (n, 2)), "labels": rng.integers(-1, 4, (n, 2)),
            "returns": rng.normal(size=(n, 2)).astype(np.float32), "discounts": np.full(n, 0.9, np.float32),
            "weights": rng.random(n).astype(np.float32), "ids": np.arange(n)}


def test_mirror_steps_mirrors_the_chosen_steps_whole_and_leaves_the_rest():
    sample = replay_sample()
    before = {k: v.copy() for k, v in sample.items()}
    which = np.arange(64) % 3 == 0
    out = mirror_steps(sample, which)
    for key, value in before.items():  # the sample given is not written to
        assert (sample[key] == value).all()
    for key in ("obs", "next_obs"):
        assert (out[key][which] == sample[key][which][:, :, ::-1]).all()
        assert (out[key][~which] == sample[key][~which]).all()
    assert (out["actions"][which] == MIRRORED_MOVE[sample["actions"][which]]).all()
    assert (out["actions"][~which] == sample["actions"][~which]).all()
    labels = sample["labels"]
    assert (out["labels"][labels < 0] == -1).all()  # no label stays none
    taught = which[:, None] & (labels >= 0)
    assert (out["labels"][taught] == MIRRORED_MOVE[labels[taught]]).all()
    assert (out["labels"][~which] == labels[~which]).all()
    for key in ("returns", "discounts", "weights", "ids"):
        assert (out[key] == sample[key]).all()


def test_a_mirrored_step_answers_the_mirrored_leader_move_with_the_mirrored_move():
    sample = replay_sample()
    rng = np.random.default_rng(1)
    sample["answers"] = rng.integers(-1, 4, (64, 2, 4))
    which = np.arange(64) % 2 == 0
    out = mirror_steps(sample, which)
    answers = sample["answers"]
    assert (out["answers"][~which] == answers[~which]).all()
    for move in range(4):  # the answer to a move, mirrored, is the answer to the mirrored move
        before, after = answers[which][..., move], out["answers"][which][..., MIRRORED_MOVE[move]]
        assert (after[before < 0] == -1).all()
        assert (after[before >= 0] == MIRRORED_MOVE[before[before >= 0]]).all()


def test_a_mirrored_step_accepts_the_mirrored_joint_actions():
    sample = replay_sample()
    sample["accepted"] = np.random.default_rng(2).integers(0, 1 << 16, 64)
    which = np.arange(64) % 2 == 0
    out = mirror_steps(sample, which)
    assert (out["accepted"][~which] == sample["accepted"][~which]).all()
    for leader, follower in itertools.product(range(4), repeat=2):  # (l, f) accepted <=> its mirror is, mirrored
        before = sample["accepted"][which] >> (4 * leader + follower) & 1
        after = out["accepted"][which] >> (4 * MIRRORED_MOVE[leader] + MIRRORED_MOVE[follower]) & 1
        assert (before == after).all()
    # e.g. forward-left for both (1, 1) becomes forward-right for both (2, 2)
    assert mirror_joint_masks(np.array([1 << 5, 1 << 4])).tolist() == [1 << 10, 1 << 8]


def test_the_learner_mirrors_about_half_of_each_batch_with_train_mirror():
    pytest.importorskip("ray")
    from formation.learn.algorithm import build_algorithm_config
    from formation.learn.rollout_actor import module_of_agent, spaces_of

    for mirror in (False, True):
        run = RunConfig.load("configs/setting1.yaml", {"train.mirror": mirror})
        spaces = {m: spaces_of(run) for m in set(module_of_agent(run))}
        learner = build_algorithm_config(run).build_learner(spaces=spaces)
        learner.set_replays([], module_of_agent(run), mirror=run.train.mirror)
        sample = replay_sample()
        out = learner.augment(sample)
        flipped = np.array([(out["obs"][i] != sample["obs"][i]).any() for i in range(64)])
        if not mirror:
            assert out is sample
            continue
        assert 16 <= flipped.sum() <= 48
        assert (out["obs"][flipped] == sample["obs"][flipped][:, :, ::-1]).all()
        assert (out["actions"][flipped] == MIRRORED_MOVE[sample["actions"][flipped]]).all()


def test_train_mirror_on_a_board_that_is_not_its_own_mirror_is_a_one_line_error():
    with pytest.raises(ConfigError, match=r"^train\.mirror: true needs a board of odd width, whose destination is "
                                          r"its middle column \(not width 50\); allowed: false, or true on settings "
                                          r"1-2$"):
        RunConfig.load("configs/setting3.yaml", {"train.mirror": True})
    with pytest.raises(ConfigError, match=r"^train\.mirror: 'yes please' is not allowed; allowed: true, false$"):
        RunConfig.load("configs/setting1.yaml", {"train.mirror": "yes please"})
    assert RunConfig.load("configs/setting2.yaml", {"train.mirror": True}).train.mirror
