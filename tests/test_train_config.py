"""The training config: defaults, YAML loading, overrides, and one-line errors naming the key."""

import dataclasses
import re

import pytest
import yaml

from formation.config import ConfigError
from formation.recipe.config import RunConfig, TeacherSettings


def one_line_error(values=None, path=None, overrides=None) -> str:
    with pytest.raises(ConfigError) as err:
        if path is not None:
            RunConfig.load(path, overrides)
        else:
            RunConfig.from_dict(values)
    message = str(err.value)
    assert "\n" not in message
    return message


def test_round_trip_through_a_dict():
    config = RunConfig.from_dict({"game": {"setting": 2, "obs_type": "grid"}, "train": {"gamma": 0.9}})
    assert config.game.formation == "vertical" and config.train.gamma == 0.9
    assert RunConfig.from_dict(config.to_dict()) == config


def test_yaml_and_dotted_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("game:\n  setting: 3\ntrain:\n  n_step: 5\n")
    config = RunConfig.load(path, {"train.n_step": 2, "game.n_followers": 2, "resources.games_per_actor": 4})
    assert (config.game.height, config.train.n_step, config.game.n_followers) == (50, 2, 2)
    assert config.resources.games_per_actor == 4


def test_numbers_in_exponent_notation_are_numbers_in_a_file_and_in_overrides(tmp_path):
    from formation.cli import parse_overrides

    path = tmp_path / "c.yaml"
    path.write_text("train:\n  lr: 3e-4\nteacher:\n  margin_gap: 5E+0\n")
    config = RunConfig.load(path, parse_overrides(["teacher.safety_weight=1e-1", "train.shaping=0"]))
    assert (config.train.lr, config.teacher.margin_gap, config.teacher.safety_weight) == (3e-4, 5.0, 0.1)
    assert config.train.shaping == 0
    # still a one-line error where a whole number is needed
    assert one_line_error(path=path, overrides=parse_overrides(["train.total_env_steps=1e5"])).startswith(
        "train.total_env_steps")


@pytest.mark.parametrize("values, names", [
    ({"trian": {}}, "trian"),
    ({"train": {"gama": 0.9}}, "train.gama"),
    ({"train": {"gamma": 1.5}}, "train.gamma"),
    ({"train": {"n_step": 0}}, "train.n_step"),
    ({"train": {"path": "apex"}}, "train.path"),
    ({"resources": {"games_per_actor": 0}}, "resources.games_per_actor"),
    ({"game": {"setting": 9}}, "game.setting"),
    ({"game": {"d_min": 4}}, "game.d_min"),
    ({"game": {"obs_type": "rgb"}}, "game.obs_type"),
    ({"teacher": {"robust_first_step": "yes"}}, "teacher.robust_first_step"),
    ({"train": {"screen_cells": "yes"}}, "train.screen_cells"),
    ({"train": {"obstacle_forecast": "yes"}}, "train.obstacle_forecast"),
    ({"train": {"obstacle_forecast": True, "screen_cells": False}}, "train.obstacle_forecast"),
    ({"game": {"frame_stack": 1}, "train": {"obstacle_forecast": True}}, "train.obstacle_forecast"),
    ({"game": {"obstacle_speeds": [1, 3]}}, "train.obstacle_forecast"),
    ({"train": {"follower_answers_leader": "yes"}}, "train.follower_answers_leader"),
    ({"teacher": {"answer_every_leader_move": "yes"}}, "teacher.answer_every_leader_move"),
    ({"train": {"follower_answers_leader": False}, "teacher": {"answer_every_leader_move": True}},
     "teacher.answer_every_leader_move"),
    ({"train": {"potential": "planner"}}, "train.potential"),
    ({"teacher": {"safety_horizon": "path"}}, "teacher.safety_horizon"),
    ({"teacher": {"margin_gap": -1}}, "teacher.margin_gap"),
    ({"teacher": {"demonstrations": 2}}, "teacher.demonstrations"),
    ({"teacher": {"dagger": True}}, "teacher.dagger"),  # the teacher always labels: no such key
    ({"train": {"dagger": True}}, "train.dagger: moved to the teacher section in 0.4 (a teacher section turns"),
    ({"train": {"margin": 5.0}}, "train.margin: moved to the teacher section in 0.4 (it is teacher.margin)"),
    ({"teacher": {}, "game": {"setting": None, "height": 9, "width": 12, "n_followers": 3, "leader_start": [6, 4],
                              "follower_starts": [[8, 2], [8, 6], [8, 4]]}}, "teacher"),  # 3 followers: no planner
    ({"train": {"leader_window": [1, 2]}}, "train.leader_window"),
    ({"train": {"leader_window": [1, 2, -3]}}, "train.leader_window"),
    ({"train": {"destination_compass": "yes"}}, "train.destination_compass"),
    ({"train": {"destination_compass": True, "leader_window": None}}, "train.destination_compass"),
    ({"train": {"path": "stock"}}, "train.path"),  # the default recipe is not RLlib's stock DQN
    ({"eval": {"episodes": 2, "gif_episodes": 3}}, "eval.gif_episodes"),
])
def test_bad_values_name_the_key(values, names):
    assert one_line_error(values).startswith(names)


# every option that was removed, at a value that did something: (key, value)
REMOVED_VALUES = [("lr_end", 1e-5), ("failure_restarts", 0.25), ("mirror", True), ("row_scan", 8),
                  ("label_order", "toward"), ("label_preference", 0.1), ("safety_priority", 1.0),
                  ("rollout_veto", True), ("safety_slack", 1), ("tolerant_formation", True),
                  ("follower_labels", "response"), ("any_shortest_move", "leader"),
                  ("followers_share_policy", False), ("potential", "none")]


@pytest.mark.parametrize("key, value", REMOVED_VALUES)
def test_a_removed_option_that_would_do_something_is_refused_in_one_line_naming_it(tmp_path, key, value):
    from formation.recipe.config import REMOVED

    assert {k for k, _ in REMOVED_VALUES} == set(REMOVED)
    message = one_line_error({"train": {key: value}})
    version = REMOVED[key][2]
    assert message.startswith(f"train.{key}: removed in {version} (") and message.endswith("/ absent")
    if key == "potential":  # a saved run's `potential: none` reads as `shaping: 0` (the test below)
        return
    # a saved run's config.yaml (formation train --resume, formation.policy.load) alike
    saved = RunConfig().to_dict()
    saved["train"][key] = value
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(saved))
    with pytest.raises(ConfigError, match=rf"^train\.{key}: removed in {re.escape(version)} "):
        RunConfig.load_saved(tmp_path / "config.yaml")


def test_a_saved_run_that_names_removed_options_at_their_neutral_values_loads_without_them(tmp_path):
    from formation.recipe.config import REMOVED

    saved = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid"}}).to_dict()
    # what 0.1 wrote into every run folder's config.yaml, and 0.2 (any_shortest_move)
    saved["train"].update(lr_end=None, failure_restarts=0.0, mirror=False, row_scan=0, label_order="lockstep",
                          label_preference=0.0, safety_priority=0.0, rollout_veto=False, safety_slack=0,
                          tolerant_formation=False, follower_labels="teacher", any_shortest_move="none",
                          followers_share_policy=True, potential="distance")
    assert set(REMOVED) <= set(saved["train"])
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(saved))
    config = RunConfig.load_saved(path)
    assert config == RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid"}})
    assert not set(REMOVED) & set(config.to_dict()["train"])


def test_missing_file_and_bad_yaml(tmp_path):
    assert "no such file" in one_line_error(path=tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("train: [1, 2\n")
    assert "not valid YAML" in one_line_error(path=bad)
    good = tmp_path / "good.yaml"
    good.write_text("train: {}\n")
    assert "section.key" in one_line_error(path=good, overrides={"gamma": 0.5})


def test_every_shipped_config_is_valid():
    from pathlib import Path

    configs = sorted(Path("configs").glob("**/*.yaml"))
    assert {"paper.yaml", "smoke.yaml", "small.yaml"} <= {p.name for p in configs}
    for path in configs:
        RunConfig.load(path)


def test_the_reward_only_configs_train_without_the_planner_and_the_settings_with_it():
    from pathlib import Path

    reward_only = sorted(Path("configs/reward_only").glob("*.yaml"))
    assert reward_only
    for path in reward_only:
        run = RunConfig.load(path)
        assert run.planner_options == [], path
        assert run.game.obs_type == "pixels" and run.game.frame_stack == 4  # from pixels, as the paper
    assert RunConfig.load("configs/setting2.yaml").planner_options == [
        "teacher", "teacher.demonstrations", "teacher.safety_horizon", "refit.rounds"]
    assert RunConfig.load("configs/paper.yaml").planner_options == []


def test_a_config_with_a_game_section_alone_trains_from_the_reward_alone_as_the_reward_only_configs(tmp_path):
    bare = RunConfig.from_dict({"game": {"setting": 3, "obs_type": "pixels", "frame_stack": 4}})
    assert bare.teacher is None and bare.planner_options == []
    shipped = RunConfig.load("configs/reward_only/setting3.yaml")
    # the shipped configs differ from the bare default in their budget and their averaged team alone
    assert shipped.train == dataclasses.replace(bare.train, total_env_steps=shipped.train.total_env_steps,
                                                average_decay=shipped.train.average_decay)
    # an empty teacher section turns the teacher on, with its defaults
    assert RunConfig.from_dict({"teacher": {}}).teacher == TeacherSettings()
    assert "teacher" not in bare.to_dict() and RunConfig.from_dict(RunConfig.from_dict({"teacher": {}}).to_dict())\
        .teacher == TeacherSettings()


# what a run folder's config.yaml held before the teacher had a section of its own
OLD_TEACHER = dict(dagger=True, demonstrations=0.5, margin=5.0, margin_gap=5.0, planner_slack=6,
                   robust_first_step=True, answer_every_leader_move=True, safety_horizon=4, safety_weight=1.0,
                   safety_encoder=True, potential="distance")


def test_a_saved_run_from_before_the_teacher_section_loads_with_its_teacher_or_without_one(tmp_path):
    saved = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid"}}).to_dict()
    saved["train"].update(OLD_TEACHER)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(saved))
    run = RunConfig.load_saved(path)
    assert run.teacher == TeacherSettings(answer_every_leader_move=True, safety_horizon=4, safety_encoder=True)
    # a reward-only run of then: no labels, no demonstrations, the paper's reward unshaped
    saved["train"].update(dagger=False, demonstrations=0, margin=0, safety_horizon=0, safety_encoder=False,
                          potential="none")
    path.write_text(yaml.safe_dump(saved))
    run = RunConfig.load_saved(path)
    assert run.teacher is None and run.train.shaping == 0
    # the planner's games without its labels are gone: refused in one line naming the key
    saved["train"].update(demonstrations=0.5)
    path.write_text(yaml.safe_dump(saved))
    with pytest.raises(ConfigError, match=r"^train\.dagger: false with train\.demonstrations"):
        RunConfig.load_saved(path)


@pytest.mark.parametrize("folder", ["configs", "configs/reward_only"])
def test_the_four_settings_configs_share_one_recipe_and_differ_in_the_setting_and_the_budget(folder):
    """... and in whether they keep the averaged team, one decay for all, which the configs take up as each is run
    again with it (configs/reward_only/setting1.yaml, setting2.yaml so far)."""
    def recipe(k: int) -> dict:
        values = yaml.safe_load(open(f"{folder}/setting{k}.yaml"))
        assert values["game"]["setting"] == k
        assert values["train"].pop("average_decay", 0.999) == 0.999
        for section, key in (("game", "setting"), ("train", "total_env_steps")):
            del values[section][key]
        return values

    assert all(recipe(k) == recipe(1) for k in (2, 3, 4))


def test_paper_config_is_the_papers_table_2():
    paper = RunConfig.load("configs/paper.yaml")
    t = paper.train
    assert (t.batch_size, t.replay_capacity, t.gamma, t.lr, t.epsilon_start, t.epsilon_end) == (
        32, 50000, 0.99, 1e-4, 1.0, 0.1)
    assert t.shaping == 0 and paper.game.obs_type == "pixels" and paper.game.frame_stack == 4
    # none of our recipe: no teacher, each agent explores on its own, one-step targets
    assert t.leader_window is None and not t.screen_cells  # the paper's networks see the whole screen in patches
    assert not t.obstacle_forecast  # and learn the obstacles' motion themselves
    assert not t.follower_answers_leader  # and choose at once, each on its own
    assert paper.teacher is None and (t.exploration, t.n_step, t.prioritized) == ("independent", 1, False)
    assert t.reward_formation_kept is None and not t.team_reward  # the paper's reward, unshaped
    assert paper.game.max_steps == 200 and paper.game.reward_reach == 50


def test_a_saved_run_from_before_a_key_existed_keeps_what_it_trained_with(tmp_path):
    saved = RunConfig.from_dict({"game": {"setting": 1, "obs_type": "grid"}}).to_dict()
    del saved["train"]["leader_window"]  # written before the leader window existed: whole-screen networks
    del saved["train"]["screen_cells"]  # and before screens were read per cell: 4x4-pixel patches
    del saved["train"]["obstacle_forecast"]
    del saved["train"]["follower_answers_leader"]
    for key in ("reward_formation_kept", "team_reward"):  # the paper's reward
        del saved["train"][key]
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(saved))
    assert RunConfig.load_saved(path).train.leader_window is None
    assert RunConfig.load_saved(path).train.screen_cells is False
    assert RunConfig.load_saved(path).train.obstacle_forecast is False
    assert RunConfig.load_saved(path).train.follower_answers_leader is False
    old = RunConfig.load_saved(path).train
    assert (old.reward_formation_kept, old.team_reward) == (None, False)
    assert RunConfig.load(path).train.leader_window == (12, 3, 10)  # a plain config takes today's default
    assert RunConfig.load(path).train.screen_cells is True
    assert RunConfig.load(path).train.obstacle_forecast is True
    assert RunConfig.load(path).train.follower_answers_leader is True
    saved["train"]["leader_window"] = [4, 1, 2]
    path.write_text(yaml.safe_dump(saved))
    assert RunConfig.load_saved(path).train.leader_window == (4, 1, 2)
