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


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def play_greedy(config: GameConfig, act: Callable[[np.ndarray], np.ndarray], episodes: int, seed: int,
                record: int = 0, watch: Callable[[BatchedGame, np.ndarray, np.ndarray], None] | None = None) -> dict:
    """Play ``episodes`` episodes at once; per-episode outcomes and summary rates. ``record`` > 0 also
    returns the screens of the first ``record`` episodes (``"screens"``: one list of frames each, from
    the start to the episode's last step). ``watch(game, actions, live)``, if given, sees every step's
    state and actions before the step is played (the live games are those still playing)."""
    game = BatchedGame(config, batch_size=episodes, seed=seed)
    game.reset()
    renderer = ScreenRenderer(game) if record else None
    screens: list[list[np.ndarray]] = [[] for _ in range(min(record, episodes))]

    def snapshot(live: np.ndarray) -> None:
        if renderer is not None:
            frames = renderer.render()
            for i, episode in enumerate(screens):
                if live[i]:
                    episode.append(frames[i].copy())
    scenarios = [game.scenario(i).to_dict() for i in range(episodes)]
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
