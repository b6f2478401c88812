"""The trained policies shipped in policies/ load from a fresh clone, play their own setting from
pixels, and still reach what docs/RESULTS.md reports (within sampling noise of a short check)."""

import json
from pathlib import Path

import pytest

from formation.evaluate import play_greedy
from formation.game import BatchedGame
from formation.policy import load, training_line

REPO = Path(__file__).resolve().parent.parent
SEED = 2_000_000  # docs/RESULTS.md evaluates from here: scenarios no training run used
EPISODES = 50  # eight policies, four of them on 50x50 boards: the suite's time matters


def first_scenarios(game, reported: dict, n: int) -> list[dict]:
    """The first ``n`` of the scenarios a report played (a batch of other size draws other games)."""
    games = BatchedGame(game, batch_size=reported["episodes"], seed=reported["seed"])
    games.reset()
    return [games.scenario(i).to_dict() for i in range(n)]


# the teacher's policies, and those learnt from the reward alone that have shipped so far
SHIPPED = [("", k) for k in (1, 2, 3, 4)] + [("reward_only", int(p.name.removeprefix("setting")))
                                            for p in sorted((REPO / "policies" / "reward_only").glob("setting*"))]


@pytest.mark.parametrize(("family", "setting"), SHIPPED, ids=[f"{f or 'teacher'}-setting{k}" for f, k in SHIPPED])
def test_a_shipped_policy_plays_its_setting_from_pixels_as_reported(family, setting):
    folder = REPO / "policies" / family / f"setting{setting}"
    policy = load(folder)
    assert policy.game.setting == setting
    assert policy.game.obs_type == "pixels" and policy.game.frame_stack == 4
    assert sum(f.stat().st_size for f in folder.iterdir()) < 6_000_000  # a few MB (settings 2-4 with safety heads: 5.0)
    reported = json.loads((REPO / "docs" / "results" / family / f"setting{setting}.json").read_text())
    if family == "reward_only":  # its card's run config: no planner took part in training
        assert reported["trained"]["planner_options"] == []
        assert training_line(policy.training).endswith("from the reward alone, no planner")
    assert reported["episodes"] == 1000 and reported["env_steps"] == policy.env_steps
    summary = play_greedy(policy.game, policy.act_batch, EPISODES, SEED,
                          scenarios=first_scenarios(policy.game, reported, EPISODES))["summary"]
    # the first 50 of the 1000 reported scenarios: far above chance (random play: 0%), and
    # within about three standard errors of the reported rate
    p = reported["success"]
    assert summary["success"] >= max(0.3, p - 3 * (p * (1 - p) / EPISODES) ** 0.5 - 0.01), (summary, p)



# every shipped team and the config file that makes it
MADE_BY = [(f"policies/{family}/setting{k}".replace("//", "/"), f"configs/{family}/setting{k}.yaml".replace("//", "/"))
           for family, k in SHIPPED] + [("policies/generalist", "configs/generalist.yaml")]


@pytest.mark.parametrize(("folder", "config"), MADE_BY, ids=[f for f, _ in MADE_BY])
def test_a_shipped_policy_was_trained_with_its_config_file_alone(folder, config):
    """The run config a card saved is its config file's, with the card's seed (``--set train.seed=S``): the
    file's command makes the team again, with no option of a draft or of the command line."""
    from formation.recipe.config import RunConfig

    training = load(REPO / folder).training
    saved = RunConfig.from_saved(training["config"])
    assert saved.to_dict() == RunConfig.load(REPO / config, {"train.seed": saved.train.seed}).to_dict()
    assert training["commit"]  # the code that made it

def test_a_card_that_names_a_removed_option_loads_at_its_neutral_value_and_is_refused_at_another(tmp_path):
    from formation.policy import PolicyError

    folder = tmp_path / "setting1"
    folder.mkdir()
    for f in (REPO / "policies" / "setting1").iterdir():
        (folder / f.name).write_bytes(f.read_bytes())
    card = json.loads((folder / "policy.json").read_text())
    for net in card["networks"].values():
        net["row_scan"] = 0  # as 0.1 wrote every card
    (folder / "policy.json").write_text(json.dumps(card))
    assert load(folder).specs == load(REPO / "policies" / "setting1").specs
    card["networks"]["follower"]["row_scan"] = 8
    (folder / "policy.json").write_text(json.dumps(card))
    with pytest.raises(PolicyError, match=r"policy\.json': networks\.follower\.row_scan: removed in 0\.2 \(.*"
                                          r"allowed: 0 / absent$"):
        load(folder)


GENERALIST = sorted((REPO / "docs" / "results" / "generalist").glob("setting*_followers*.json"))


@pytest.mark.parametrize("report", GENERALIST, ids=[p.stem for p in GENERALIST])
def test_the_generalist_plays_each_of_its_games_from_pixels_as_reported(report):
    """`policies/generalist`: one team for every setting and 1-3 followers (`configs/generalist.yaml`)."""
    reported = json.loads(report.read_text())
    policy = load(REPO / "policies" / "generalist")
    assert reported["trained"]["planner_options"] == [] and reported["env_steps"] == policy.env_steps
    games = policy.training["config"]["games"]
    assert reported["setting"] in games["settings"] and reported["followers"] in games["followers"]
    game = policy.for_game(setting=reported["setting"], n_followers=reported["followers"])
    episodes = 20  # twelve games: the first 20 of each report's scenarios
    summary = play_greedy(game.game, game.act_batch, episodes, reported["seed"],
                          scenarios=first_scenarios(game.game, reported, episodes))["summary"]
    p = reported["success"]
    assert summary["success"] >= p - 3 * (p * (1 - p) / episodes) ** 0.5 - 0.01, (summary, p)
