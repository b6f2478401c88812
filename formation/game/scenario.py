"""Scenarios: the game's full state in plain lists, to start a game from or to save a moment.

``{"leader": [r, c], "follower": [r, c], "obstacles": [[r, c, v], ...]}``; with more than one
follower ``"followers": [[r, c], ...]`` replaces ``"follower"``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from formation.config import ConfigError, GameConfig, formation_broken_by


@dataclass(frozen=True)
class Scenario:
    leader: tuple[int, int]
    followers: tuple[tuple[int, int], ...]
    obstacles: tuple[tuple[int, int, int], ...]  # (row, col, velocity)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"leader": list(self.leader)}
        if len(self.followers) == 1:
            out["follower"] = list(self.followers[0])
        else:
            out["followers"] = [list(f) for f in self.followers]
        out["obstacles"] = [list(o) for o in self.obstacles]
        return out


def _bad(message: str) -> None:
    raise ConfigError(f"scenario: {message}")


def _is_int(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


def _cell(name: str, value: Any, config: GameConfig) -> tuple[int, int]:
    if not isinstance(value, list | tuple | np.ndarray) or len(value) != 2 or not all(map(_is_int, value)):
        _bad(f"{name} {value!r} is not allowed; allowed: a [row, col] pair of integers")
    r, c = int(value[0]), int(value[1])
    if not (0 <= r < config.height and 0 <= c < config.width):
        _bad(f"{name} {[r, c]} lies off the {config.height}x{config.width} board")
    return (r, c)


def parse_scenario(scenario: Any, config: GameConfig) -> Scenario:
    """Check a scenario against the config; a bad one raises ConfigError naming the entry."""
    if isinstance(scenario, Scenario):
        scenario = scenario.to_dict()
    if not isinstance(scenario, dict):
        _bad(f"{type(scenario).__name__} is not allowed; allowed: a dict with leader, follower(s), obstacles")
    k = config.n_followers
    follower_key = "follower" if k == 1 else "followers"
    allowed = {"leader", follower_key, "obstacles"}
    for key in scenario:
        if key not in allowed:
            _bad(f"unknown key {key!r}; allowed: {', '.join(sorted(allowed))}")
    for key in allowed:
        if key not in scenario:
            _bad(f"missing key {key!r}; a scenario needs {', '.join(sorted(allowed))}")
    leader = _cell("leader", scenario["leader"], config)
    if k == 1:
        followers = (_cell("follower", scenario["follower"], config),)
    else:
        raw = scenario["followers"]
        if not isinstance(raw, list | tuple) or len(raw) != k:
            _bad(f"followers must list {k} [row, col] cells (n_followers={k})")
        followers = tuple(_cell(f"followers[{i}]", f, config) for i, f in enumerate(raw))
    raw_obstacles = scenario["obstacles"]
    if not isinstance(raw_obstacles, list | tuple):
        _bad("obstacles must be a list of [row, col, velocity] triples")
    obstacles = []
    for i, o in enumerate(raw_obstacles):
        if not isinstance(o, list | tuple | np.ndarray) or len(o) != 3 or not all(map(_is_int, o)):
            _bad(f"obstacles[{i}] {o!r} is not allowed; allowed: [row, col, velocity] integers")
        r, c = _cell(f"obstacles[{i}]", o[:2], config)
        if int(o[2]) == 0:
            _bad(f"obstacles[{i}] has velocity 0; allowed: a non-zero integer (sign = direction)")
        obstacles.append((r, c, int(o[2])))
    cells = [leader, *followers, *((r, c) for r, c, _ in obstacles)]
    if len(set(cells)) != len(cells):
        _bad("two entities overlap on one cell")
    if leader == config.destination:
        _bad(f"the leader starts on the destination {list(config.destination)}")
    broken = formation_broken_by(config, leader, followers)
    if broken:
        _bad(f"the formation is broken: {broken}")
    return Scenario(leader, followers, tuple(obstacles))
