"""The clairvoyant planner: its paths replay to success in the environment, it is exact (checked
against a brute force that steps the game itself), and it says None when there is no way through."""

from __future__ import annotations

import numpy as np
import pytest

from formation import planner
from formation.config import ConfigError, GameConfig
from formation.env import parallel_env
from formation.game import BatchedGame, Scenario, parse_scenario
from formation.planner import (
    FirstMovesAhead,
    lower_bound,
    paths_exist,
    shortest_first_moves_many,
    shortest_path,
    surviving_first_moves_many,
)

TINY = dict(height=7, width=7, n_obstacles=2, max_steps=14)  # small enough for the brute force


def replay(path, scenario: dict, setting: int, **overrides) -> int:
    """Play ``path`` in the PettingZoo env from ``scenario``; the step count at success (asserting
    that no earlier step ends the episode and that the last one is a success)."""
    env = parallel_env(setting, frame_stack=1, **overrides)
    env.reset(options={"scenario": scenario})
    for step, joint in enumerate(path, start=1):
        _, _, terminations, truncations, infos = env.step(dict(zip(env.possible_agents, joint, strict=True)))
        if terminations["leader"] or truncations["leader"]:
            assert step == len(path), f"the episode ended at step {step} of {len(path)}: {infos['leader']}"
    assert infos["leader"]["success"], infos["leader"]
    return step


def random_scenario(seed: int, setting: int, **overrides) -> dict:
    env = parallel_env(setting, frame_stack=1, **overrides)
    env.reset(seed=seed)
    return env.scenario()


def brute_force_length(scenario, config: GameConfig, max_len: int) -> int | None:
    """Fewest steps to success by the game's own ``step``: every joint action from every distinct
    full game state (agents and obstacles), layer after layer. It shares nothing with the planner
    but the rules; its one pruning is dropping leaders too far from the destination for max_len."""
    start = parse_scenario(scenario, config)
    n_agents = 1 + config.n_followers
    grid = np.meshgrid(*[np.arange(4)] * n_agents, indexing="ij")
    joint = np.stack([g.ravel() for g in grid], axis=1)
    dest_row, dest_col = config.destination
    root = BatchedGame(config, 1)
    root.load([start])
    positions, cols, dirs = root.positions.copy(), root.obstacle_cols.copy(), root.obstacle_dirs.copy()
    kids = None
    for t in range(min(max_len, config.max_steps)):
        size = len(positions) * len(joint)
        if kids is None or kids.batch_size < size:
            kids = BatchedGame(config, size)
            kids.load([start] * size)  # obstacle rows and speeds; the rest is overwritten below
        kids.positions[:size] = np.repeat(positions, len(joint), axis=0)
        kids.obstacle_cols[:size] = np.repeat(cols, len(joint), axis=0)
        kids.obstacle_dirs[:size] = np.repeat(dirs, len(joint), axis=0)
        kids.steps[:] = t
        actions = np.zeros((kids.batch_size, n_agents), np.intp)
        actions[:size] = np.tile(joint, (len(positions), 1))
        kids.step(actions)
        if kids.success[:size].any():
            return t + 1
        leader = kids.positions[:size, 0]
        to_go = np.maximum(leader[:, 0] - dest_row, np.abs(leader[:, 1] - dest_col))
        alive = np.flatnonzero(~kids.done[:size] & (to_go <= max_len - t - 1))
        if len(alive) == 0:
            return None
        state = np.concatenate([kids.positions[alive].reshape(len(alive), -1), kids.obstacle_cols[alive],
                                kids.obstacle_dirs[alive]], axis=1)
        distinct = alive[np.unique(state, axis=0, return_index=True)[1]]
        positions = kids.positions[distinct].copy()
        cols, dirs = kids.obstacle_cols[distinct].copy(), kids.obstacle_dirs[distinct].copy()
    return None


def tiny_scenarios(setting: int, n: int, **overrides):
    """Random scenarios of a tiny board (skipping the few where an obstacle starts on an agent)."""
    config = GameConfig.from_setting(setting, **{**TINY, **overrides})
    game = BatchedGame(config, 1)
    for seed in range(n):
        game.reset(seed=seed)
        scenario = game.scenario(0)
        try:
            parse_scenario(scenario, config)
        except ConfigError:
            continue
        yield seed, scenario, config


# ---------------------------------------------------------------------------- replays
REPLAYED = [(s, i) for s in (1, 2) for i in range(5)] + [(3, 0), (4, 0), (4, 1)]


@pytest.mark.parametrize("setting,seed", REPLAYED)
def test_path_replays_to_success(setting, seed):
    scenario = random_scenario(seed, setting)
    path = shortest_path(scenario, setting)
    assert path is not None
    assert all(len(joint) == 2 and all(type(a) is int and 0 <= a <= 3 for a in joint) for joint in path)
    assert len(path) >= lower_bound(scenario, GameConfig.from_setting(setting))
    assert replay(path, scenario, setting) == len(path)


def test_two_followers_replay_to_success():
    small = dict(n_followers=2, height=12, width=12, n_obstacles=2)
    config = GameConfig.from_setting(1, **small)
    for seed in range(3):
        scenario = random_scenario(seed, 1, **small)
        path = shortest_path(scenario, config=config)
        assert path is not None and all(len(joint) == 3 for joint in path)
        assert len(path) >= lower_bound(scenario, config)
        assert replay(path, scenario, 1, **small) == len(path)


# ---------------------------------------------------------------------------- exactness
def test_matches_brute_force_where_detours_are_needed():
    checked = {"detour": 0, "none": 0, "lower bound": 0}
    for setting in (1, 2):
        for seed, scenario, config in tiny_scenarios(setting, 40):
            path = shortest_path(scenario, config=config)
            bound = lower_bound(scenario, config)
            kind = "none" if path is None else "detour" if len(path) > bound else "lower bound"
            if checked[kind] >= {"detour": 10, "none": 3, "lower bound": 3}[kind]:
                continue
            checked[kind] += 1
            expected = brute_force_length(scenario, config, config.max_steps)
            assert (None if path is None else len(path)) == expected, (setting, seed)
            if path is not None:
                assert replay(path, scenario.to_dict(), setting, **TINY) == len(path)
    assert checked == {"detour": 10, "none": 3, "lower bound": 3}


def test_two_followers_match_brute_force():
    found = 0
    for seed, scenario, config in tiny_scenarios(1, 20, n_followers=2, max_steps=10):
        path = shortest_path(scenario, config=config)
        if path is not None and len(path) > lower_bound(scenario, config):
            assert len(path) == brute_force_length(scenario, config, config.max_steps), seed
            found += 1
            if found == 2:
                return
    pytest.fail("no tiny two-follower scenario needing a detour")


def test_first_moves_are_exactly_the_joint_actions_that_start_a_shortest_path():
    """Every joint action is played once with the game; it starts a shortest path when it wins at
    once on a one-step path, or the brute force finds the rest one step shorter."""
    import itertools

    checked = 0
    # two followers take 64 joint actions and a brute force of 64 children a state each: fewer of their scenarios
    # (seeds 8-10 of 12 were most of this test's time), more of the one-follower boards (a fraction of a second each)
    for setting, n_followers, scenarios in ((1, 1, 16), (2, 1, 16), (1, 2, 8)):
        for seed, scenario, config in tiny_scenarios(setting, scenarios, n_followers=n_followers, max_steps=10):
            found = shortest_first_moves_many([scenario], config=config)[0]
            path = shortest_path(scenario, config=config)
            if path is None:
                assert found is None
                continue
            length, moves = found
            assert length == len(path) and tuple(int(a) for a in path[0]) in moves
            probe, expected = BatchedGame(config, 1), []
            for joint in itertools.product(range(4), repeat=1 + n_followers):
                probe.load([scenario])
                probe.step(np.array([joint]))
                if probe.done[0]:
                    starts = bool(probe.success[0]) and length == 1
                else:
                    starts = brute_force_length(probe.scenario(0), config, length - 1) == length - 1
                if starts:
                    expected.append(joint)
            assert moves == expected, (setting, n_followers, seed)
            checked += 1
    assert checked >= 20


def played_states(setting: int, seeds, steps: int, **overrides) -> tuple[GameConfig, list[Scenario]]:
    """States of random games of a setting after 0 to ``steps`` steps of a fixed mix of moves
    (those still playing), so the batch holds many leader places and obstacle speeds."""
    config = GameConfig.from_setting(setting, **overrides)
    game, out = BatchedGame(config, 1), []
    for seed in seeds:
        game.reset(seed=seed)
        for t in range(steps + 1):
            if game.done[0]:
                break
            out.append(game.scenario(0))
            game.step(np.array([[t % 4, (t * 3 + seed) % 4]]))
    return config, out


@pytest.mark.parametrize("setting", [1, 2])
def test_many_scenarios_searched_at_once_get_each_their_own_answer(setting):
    """One batched search of many states (each with its own obstacles, speeds and step limit, some
    too short for any path) answers for each what a search of it alone answers."""
    config, states = played_states(setting, range(6), 12)
    limits = [lower_bound(s, config) + (i % 5) * 2 - 1 for i, s in enumerate(states)]
    alone = [shortest_first_moves_many([s], config=config.replace(max_steps=limit))[0]
             for s, limit in zip(states, limits)]
    assert shortest_first_moves_many(states, config=config, max_steps=limits) == alone
    assert list(paths_exist(states, config=config, max_steps=limits)) == [a is not None for a in alone]
    exist = [shortest_path(s, config=config.replace(max_steps=limit)) is not None for s, limit in zip(states, limits)]
    assert exist == [a is not None for a in alone]
    assert 0 < sum(exist) < len(states)  # both kinds of answer are checked
    assert len({len(a[1]) for a in alone if a}) > 1


def test_many_scenarios_of_a_tiny_board_match_the_brute_force():
    for setting in (1, 2):
        config = GameConfig.from_setting(setting, **{**TINY, "max_steps": 10})
        batch = [scenario for _, scenario, _ in tiny_scenarios(setting, 12, max_steps=10)]
        lengths = [found[0] if found else None for found in shortest_first_moves_many(batch, config=config)]
        assert lengths == [brute_force_length(scenario, config, 10) for scenario in batch]
        assert None in lengths and len(set(lengths)) > 2


def test_a_scenario_found_valid_for_one_config_is_checked_again_for_another():
    config, states = played_states(3, range(1), 0)
    assert shortest_first_moves_many(states, config=config)[0] is not None
    assert surviving_first_moves_many(states, config=config, horizon=2)[0] > 0
    with pytest.raises(ConfigError, match="off the 25x25 board"):
        shortest_first_moves_many(states, config=GameConfig.from_setting(1))
    with pytest.raises(ConfigError, match="off the 25x25 board"):
        paths_exist(states, config=GameConfig.from_setting(1))


def test_a_batch_needs_one_limit_per_scenario():
    config, states = played_states(1, range(2), 0)
    with pytest.raises(ConfigError, match="max_steps: got 1 limits for 2 scenarios"):
        shortest_first_moves_many(states, config=config, max_steps=[10])


def test_needs_more_than_the_lower_bound():
    """Setting 2, seed 0: an obstacle forces one step beyond the lower bound of 22."""
    scenario = random_scenario(0, 2)
    assert lower_bound(scenario, GameConfig.from_setting(2)) == 22
    assert len(shortest_path(scenario, 2)) == 23
    assert shortest_path(scenario, 2, max_steps=23) is not None
    assert shortest_path(scenario, 2, max_steps=22) is None


def greedy_play_states(setting: int, n_games: int, steps: int, epsilon: float = 0.3, seed: int = 0,
                       **overrides) -> tuple[GameConfig, list[Scenario]]:
    """The states of ``n_games`` games playing ``steps`` steps (restarting as they end), each step the first move of a
    shortest path, or a random joint move with probability ``epsilon`` (and where there is no path): episodes'
    first steps, states along shortest paths, and states off them."""
    config = GameConfig.from_setting(setting, **overrides)
    game, rng, out = BatchedGame(config, n_games, seed=seed), np.random.default_rng(seed), []
    game.reset()
    for _ in range(steps):
        states = [game.scenario(i) for i in range(n_games)]
        out += states
        found = shortest_first_moves_many(states, config=config)
        actions = rng.integers(0, 4, (n_games, 1 + config.n_followers))
        for i, f in enumerate(found):
            if f is not None and rng.random() >= epsilon:
                actions[i] = f[1][int(rng.integers(len(f[1])))]
        game.step(actions)
        game.reset(mask=game.done)
    return config, out


@pytest.mark.parametrize("setting", [1, 2])
def test_searches_stepping_layers_as_codes_answer_as_those_stepping_cells(setting, monkeypatch):
    """The move table (layers as state codes) changes no answer of the searches: the same states searched
    with layers of cells, the planner's way without a table, get the same shortest first moves, path
    existence and surviving first moves."""
    config, states = greedy_play_states(setting, 8, 30)
    limits = [lower_bound(s, config) + (i % 4) * 2 - 1 for i, s in enumerate(states)]  # some too short

    def answers():
        return (shortest_first_moves_many(states, config=config, max_steps=limits),
                paths_exist(states, config=config, max_steps=limits).tolist(),
                surviving_first_moves_many(states, config=config, horizon=4).tolist())
    assert planner._board_of(config).moves(2) is not None
    fast = answers()
    monkeypatch.setattr(planner, "KEPT_MARKS", 0)  # deduplication's scratch made afresh for each search
    assert answers() == fast
    monkeypatch.setattr(planner, "MOVE_TABLE_LIMIT", 0)
    assert planner._board_of(config).moves(2) is None
    assert answers() == fast
    assert any(f is None for f in fast[0]) and any(f is not None for f in fast[0])


@pytest.mark.parametrize("width", [1, planner.BEAM_WIDTH])
def test_paths_exist_answers_as_full_searches_whatever_its_beam_finds(width, monkeypatch):
    """A beam only shortens the search where it finds a path: with a beam too narrow to find most paths or one
    as wide as the planner's, ``paths_exist`` says what the full searches say, also where a limit is too short."""
    config, states = greedy_play_states(1, 8, 30)
    limits = [lower_bound(s, config) + (i % 4) * 2 - 1 for i, s in enumerate(states)]
    full = [f is not None for f in shortest_first_moves_many(states, config=config, max_steps=limits)]
    beams = []
    monkeypatch.setattr(planner, "BEAM_WIDTH", width)
    beam = planner._beam_exists
    monkeypatch.setattr(planner, "_beam_exists", lambda *args: beams.append(beam(*args)) or beams[-1])
    assert paths_exist(states, config=config, max_steps=limits).tolist() == full
    found = np.concatenate(beams)
    assert 0 < found.sum() < sum(full) if width == 1 else found.sum() > 0.9 * sum(full)


@pytest.mark.parametrize("setting", [1, 2])
def test_first_moves_ahead_answer_as_a_search_of_the_state_itself(setting):
    """States of epsilon-greedy play asked in order, one step's batch after another, with a ``FirstMovesAhead``
    get what a search of each state alone (layers of cells, nothing kept) gets, and most states after the
    first steps are answered from what earlier searches found."""
    config, states = greedy_play_states(setting, 8, 30)
    ahead = FirstMovesAhead(config)
    limits = [lower_bound(s, config) + 6 for s in states]
    known, kept = 0, []
    for i in range(0, len(states), 8):
        batch = states[i:i + 8]
        known += sum(ahead.get(s) is not None for s in batch)
        kept += shortest_first_moves_many(batch, config=config, max_steps=limits[i:i + 8], ahead=ahead)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(planner, "MOVE_TABLE_LIMIT", 0)
        alone = [shortest_first_moves_many([s], config=config, max_steps=[limit])[0]
                 for s, limit in zip(states, limits)]
    assert kept == alone
    assert known > len(states) // 2
    # a short limit is answered from what is kept too: no path within it
    short = [s for s in states if ahead.get(s) is not None and ahead.get(s)[0] > 1][:5]
    assert short and shortest_first_moves_many(short, config=config, max_steps=[ahead.get(s)[0] - 1 for s in short],
                                               ahead=ahead) == [None] * len(short)
    with pytest.raises(ConfigError, match="ahead"):
        shortest_first_moves_many(states[:1], config=config.replace(max_steps=50), ahead=ahead)


# ---------------------------------------------------------------------------- no way through
def test_none_behind_a_wall():
    # On a 3-wide board an obstacle of speed 2 sweeps its whole row every step.
    narrow = dict(height=9, width=3, n_obstacles=1)
    config = GameConfig.from_setting(2, **narrow)
    scenario = {"leader": [6, 1], "follower": [8, 1], "obstacles": [[3, 0, 2]]}
    assert shortest_path(scenario, 2, **narrow) is None
    assert shortest_path(scenario, config=config.replace(max_steps=30)) is None
    assert brute_force_length(scenario, config.replace(max_steps=30), 30) is None
    # Without the wall the same board is crossed in the lower bound.
    open_board = {**scenario, "obstacles": []}
    path = shortest_path(open_board, 2, **{**narrow, "n_obstacles": 0})
    assert len(path) == lower_bound(open_board, config)


def test_none_when_max_steps_is_below_the_lower_bound():
    scenario = random_scenario(0, 1)
    assert shortest_path(scenario, 1, max_steps=lower_bound(scenario, GameConfig()) - 1) is None


# ---------------------------------------------------------------------------- arguments
def test_config_keyword_and_scenario_object():
    config = GameConfig.from_setting(3)
    scenario = random_scenario(2, 3)
    by_config = shortest_path(Scenario(tuple(scenario["leader"]), (tuple(scenario["follower"]),),
                                       tuple(map(tuple, scenario["obstacles"]))), config=config)
    assert by_config == shortest_path(scenario, 3)
    with pytest.raises(ConfigError):
        shortest_path(scenario, config=config, max_steps=10)


# ---------------------------------------------------------------------------- larger teams
def test_teams_too_large_to_search_get_a_lower_bound_that_the_brute_force_never_beats():
    """Three followers: the exact search is refused in one line; ``steps_bound`` (each follower alone with the
    leader) is never beaten by the brute force, and None only where the team has no path either. Up to two
    followers it is the planner's exact length."""
    from formation.planner import steps_bound

    for seed, scenario, config in tiny_scenarios(1, 3, n_followers=2, max_steps=10):
        path = shortest_path(scenario, config=config)
        assert steps_bound(scenario, config) == (None if path is None else len(path)), seed
    kinds = {"bound": 0, "none": 0}
    for seed, scenario, config in tiny_scenarios(1, 8, n_followers=3, max_steps=8):
        with pytest.raises(ConfigError, match=r"^n_followers: 3 is too large a team .* allowed: 1 to 2; "):
            shortest_path(scenario, config=config)
        bound = steps_bound(scenario, config)
        if bound is None:
            assert brute_force_length(scenario, config, config.max_steps) is None, seed
        else:
            assert bound >= lower_bound(scenario, config)
            assert brute_force_length(scenario, config, bound - 1) is None, seed  # nothing shorter
        kinds["none" if bound is None else "bound"] += 1
    assert kinds["bound"] >= 2, kinds
