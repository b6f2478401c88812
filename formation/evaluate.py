"""Greedy evaluation: play N episodes of held-out scenarios with a policy and report rates.

One code path for evaluation during training and for restored checkpoints. The episodes are
games ``0..N-1`` of a ``BatchedGame`` seeded with ``seed``, so the same seed gives the same
scenarios. ``act`` maps a batch of observations (N, h, w, c) to actions (N, 1+k).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame, Observer, ScreenRenderer
from formation.planner import EXACT_FOLLOWERS


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def play_greedy(config: GameConfig, act: Callable[[np.ndarray], np.ndarray], episodes: int, seed: int,
                record: int = 0, watch: Callable[[BatchedGame, np.ndarray, np.ndarray], None] | None = None,
                scenarios: list | None = None) -> dict:
    """Play ``episodes`` episodes at once; per-episode outcomes and summary rates. ``record`` > 0 also
    returns the screens of the first ``record`` episodes (``"screens"``: one list of frames each, from
    the start to the episode's last step). ``watch(game, actions, live)``, if given, sees every step's
    state and actions before the step is played (the live games are those still playing).
    ``scenarios`` (``episodes`` of them, e.g. part of an earlier result's ``"scenarios"``): play these
    instead of the games of ``seed``."""
    game = BatchedGame(config, batch_size=episodes, seed=seed)
    game.reset()
    if scenarios is not None:
        game.load(list(scenarios))
    renderer = ScreenRenderer(game) if record else None
    screens: list[list[np.ndarray]] = [[] for _ in range(min(record, episodes))]

    def snapshot(live: np.ndarray) -> None:
        if renderer is not None:
            frames = renderer.render()
            for i, episode in enumerate(screens):
                if live[i]:
                    episode.append(frames[i].copy())
    scenarios = [game.scenario(i).to_dict() for i in range(episodes)]  # as played
    observer = Observer(game)
    obs = observer.observe(np.ones(episodes, bool))
    live = np.ones(episodes, bool)
    outcome = {k: np.zeros(episodes, bool) for k in ("success", "leader_collided", "follower_collided", "broken",
                                                      "timeout", "reached")}
    steps = np.zeros(episodes, np.int64)
    returns = np.zeros((episodes, game.n_agents))
    no_reset = np.zeros(episodes, bool)
    snapshot(live)
    while live.any():
        actions = np.asarray(act(obs))
        actions[~live] = 3  # finished games stand still; nothing of theirs is counted
        if watch is not None:
            watch(game, actions, live)
        game.step(actions)
        snapshot(live)  # the step's outcome: a finished game shows how it ended
        returns[live] += game.rewards[live]
        ended = live & game.done
        outcome["success"] |= ended & game.success
        outcome["leader_collided"] |= ended & game.collided[:, 0]
        outcome["follower_collided"] |= ended & game.collided[:, 1:].any(axis=1)
        outcome["broken"] |= ended & ~game.formation_kept
        outcome["timeout"] |= ended & game.truncated
        outcome["reached"] |= ended & game.reached
        steps[ended] = game.steps[ended]
        live &= ~game.done
        obs = observer.observe(no_reset)
    n = episodes
    wins = int(outcome["success"].sum())
    low, high = wilson_interval(wins, n)
    summary = {"episodes": n, "success": wins / n, "success_ci95": [low, high],
               "leader_collision": float(outcome["leader_collided"].mean()),
               "follower_collision": float(outcome["follower_collided"].mean()),
               "formation_broken": float(outcome["broken"].mean()), "timeout": float(outcome["timeout"].mean()),
               "steps_success_mean": float(steps[outcome["success"]].mean()) if wins else None,
               "return_mean": {name: float(returns[:, i].mean()) for i, name in enumerate(config.agent_names)}}
    return {"summary": summary, "scenarios": scenarios, "steps": steps, "returns": returns, "screens": screens,
            **outcome}


# ---------------------------------------------------------------------- the planner as reference
def _plan_chunk(config_values: dict, scenarios: list) -> list:
    """Shortest paths of some scenarios (a worker process's share); for a team too large to search exactly,
    a lower bound on their steps instead (``formation.planner.steps_bound``)."""
    from formation.planner import shortest_path, steps_bound

    config = GameConfig.from_dict(config_values)
    if config.n_followers > EXACT_FOLLOWERS:
        return [steps_bound(s, config) for s in scenarios]
    return [shortest_path(s, config=config) for s in scenarios]


def planner_paths(config: GameConfig, scenarios: list, workers: int = 1,
                  progress: Callable[[int, int], None] | None = None) -> list:
    """The planner's shortest path of every scenario (a list of joint actions, or None), across
    ``workers`` processes; ``progress(done, total)`` after each chunk. For a team of more than
    ``formation.planner.EXACT_FOLLOWERS`` followers, a lower bound on each path's steps (or None) instead."""
    n = len(scenarios)
    workers = max(1, min(workers, n))
    chunk = max(1, min(16, math.ceil(n / workers)))
    pieces = [scenarios[i:i + chunk] for i in range(0, n, chunk)]
    paths: list = []
    if workers == 1:
        for piece in pieces:
            paths.extend(_plan_chunk(config.to_dict(), piece))
            if progress is not None:
                progress(len(paths), n)
        return paths
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        done = 0
        for result in pool.map(_plan_chunk, [config.to_dict()] * len(pieces), pieces):
            paths.extend(result)
            done += len(result)
            if progress is not None:
                progress(done, n)
    return paths


def planner_reference(config: GameConfig, scenarios: list, workers: int = 1,
                      progress: Callable[[int, int], None] | None = None) -> dict:
    """What the clairvoyant planner achieves on ``scenarios``: its shortest path is played through the
    game (``play_greedy`` on the same scenarios). Per scenario: ``solved`` (the planner has a path),
    ``steps`` (its length; -1 where unsolved), ``returns`` (n, 1+k) of playing it (the best return),
    ``success`` (the replay succeeded: True wherever solved), ``paths`` and ``exact`` (True). For a team too
    large to search exactly, ``exact`` is False: ``steps`` is a lower bound (``formation.planner.steps_bound``),
    ``solved`` says where no follower alone with the leader is proven stuck, and there is no path to replay
    (``returns`` and ``paths`` None)."""
    paths = planner_paths(config, scenarios, workers, progress)
    n = len(scenarios)
    if config.n_followers > EXACT_FOLLOWERS:
        steps = np.array([-1 if b is None else b for b in paths], np.int64)
        return {"solved": steps >= 0, "steps": steps, "returns": None, "success": steps >= 0,
                "replayed_steps": steps, "paths": None, "exact": False}
    solved = np.array([p is not None for p in paths], bool)
    steps = np.array([len(p) if p is not None else -1 for p in paths], np.int64)
    played = play_greedy(config, replay_paths(paths, 1 + config.n_followers), n, 0, scenarios=scenarios)
    return {"solved": solved, "steps": steps, "returns": played["returns"], "success": played["success"],
            "replayed_steps": played["steps"], "paths": paths, "exact": True}


def replay_paths(paths: list, n_agents: int) -> Callable[[np.ndarray], np.ndarray]:
    """An ``act`` for ``play_greedy`` that plays the given paths of joint actions, game ``i`` path ``i``
    (standing still past its end, or everywhere its path is None)."""
    n = len(paths)
    longest = max((len(p) for p in paths if p is not None), default=0)
    table = np.full((n, longest + 1, n_agents), 3, np.int64)
    for i, path in enumerate(paths):
        if path:
            table[i, :len(path)] = np.asarray(path, np.int64).reshape(len(path), n_agents)
    step = [0]

    def act(obs: np.ndarray) -> np.ndarray:
        t = min(step[0], longest)
        step[0] += 1
        return table[:, t].copy()

    return act


def compare_with_planner(played: dict, reference: dict, agent_names: list[str]) -> dict:
    """The policy's episodes (``play_greedy``) against the planner on the same scenarios.

    ``optimality_gap_mean``: the policy's steps minus the planner's, over the policy's successes;
    ``return_ratio``: the paper's measure, mean return over mean best return (the planner path's), per
    agent and for the team (sum over agents), over the scenarios the planner solves. ``planner_exact``: False
    where the planner's steps are a lower bound (a large team, ``planner_reference``): the gap is then an upper
    bound, and there are no best returns (None)."""
    success = np.asarray(played["success"], bool)
    solved = np.asarray(reference["solved"], bool)
    both = success & solved
    steps, best = np.asarray(played["steps"]), np.asarray(reference["steps"])
    gap = (steps[both] - best[both]).astype(float)
    exact = reference.get("exact", True)
    if not exact:  # no path to replay, so no best return: every ratio None
        returns = best_returns = np.zeros((0, len(agent_names)))
    else:
        returns, best_returns = np.asarray(played["returns"])[solved], np.asarray(reference["returns"])[solved]

    def ratio(mine: np.ndarray, theirs: np.ndarray) -> float | None:
        denominator = float(theirs.mean()) if theirs.size else 0.0
        return float(mine.mean()) / denominator if denominator != 0 else None

    ratios = {name: ratio(returns[:, i], best_returns[:, i]) for i, name in enumerate(agent_names)}
    ratios["team"] = ratio(returns.sum(axis=1), best_returns.sum(axis=1))
    return {"planner_exact": exact, "planner_solved": int(solved.sum()),
            "planner_steps_mean": float(best[solved].mean()) if solved.any()
            else None,
            "planner_steps_on_successes_mean": float(best[both].mean()) if both.any() else None,
            "optimality_gap_mean": float(gap.mean()) if gap.size else None,
            "optimality_gap_max": int(gap.max()) if gap.size else None,
            "best_return_mean": {name: float(best_returns[:, i].mean()) if len(best_returns) else None
                                 for i, name in enumerate(agent_names)},
            "return_ratio": ratios}


def evaluate_policy(config: GameConfig, act: Callable[[np.ndarray], np.ndarray], episodes: int, seed: int,
                    workers: int = 1, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """``formation evaluate``'s numbers: greedy play (``play_greedy``) and the planner on the same scenarios."""
    if progress is not None:
        progress("playing", 0, episodes)
    played = play_greedy(config, act, episodes, seed)
    if progress is not None:
        progress("playing", episodes, episodes)
    reference = planner_reference(config, played["scenarios"], workers,
                                  (lambda d, n: progress("planning", d, n)) if progress is not None else None)
    return {"episodes": episodes, "seed": seed, **played["summary"],
            "planner": compare_with_planner(played, reference, config.agent_names)}


def format_report(report: dict) -> str:
    """A readable table of ``evaluate_policy``'s report."""
    def pct(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.1%}"

    def num(x: float | None, digits: int = 2) -> str:
        return "n/a" if x is None else f"{x:.{digits}f}"

    low, high = report["success_ci95"]
    p = report["planner"]
    rows = [("episodes", f"{report['episodes']} (seed {report['seed']})"),
            ("success", f"{pct(report['success'])}  (95% CI {pct(low)} - {pct(high)})"),
            ("leader collision", pct(report["leader_collision"])),
            ("follower collision", pct(report["follower_collision"])),
            ("formation break", pct(report["formation_broken"])),
            ("time-out", pct(report["timeout"])),
            ("steps of successes", f"{num(report['steps_success_mean'])} (planner on the same: "
                                   f"{num(p['planner_steps_on_successes_mean'])})"),
            ("optimality gap", f"{num(p['optimality_gap_mean'])} steps mean, {p['optimality_gap_max']} max"),
            ("planner", f"solves {p['planner_solved']}/{report['episodes']}, "
                        f"{num(p['planner_steps_mean'])} steps mean")]
    if not p.get("planner_exact", True):  # a large team: the planner's steps are a lower bound
        rows[-3:] = [("steps of successes", f"{num(report['steps_success_mean'])} (the planner's, at least: "
                                            f"{num(p['planner_steps_on_successes_mean'])})"),
                     ("optimality gap", f"at most {num(p['optimality_gap_mean'])} steps mean"),
                     ("planner", f"a lower bound (each follower alone with the leader); none proven stuck in "
                                 f"{p['planner_solved']}/{report['episodes']}, {num(p['planner_steps_mean'])} "
                                 "steps mean")]
    for name, value in report["return_mean"].items():
        rows.append((f"return {name}", f"{num(value)} (best {num(p['best_return_mean'][name])}, "
                                       f"ratio {num(p['return_ratio'][name], 3)})"))
    rows.append(("return ratio, team", num(p["return_ratio"]["team"], 3)))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
