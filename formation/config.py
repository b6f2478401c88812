"""The game's configuration: one typed, validated object (rules in ``docs/GAME.md``).

``GameConfig.from_setting(1, n_followers=2)`` builds one of the paper's four named settings
with overrides. Every bad value raises ``ConfigError`` with a one-line message naming the
field and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

FORMATIONS = ("horizontal", "vertical")
OBS_TYPES = ("pixels", "grid")

# The paper's named settings (section III.E): board, obstacle count, formation.
SETTINGS: dict[int, dict[str, Any]] = {
    1: dict(height=25, width=25, n_obstacles=3, formation="horizontal"),
    2: dict(height=25, width=25, n_obstacles=3, formation="vertical"),
    3: dict(height=50, width=50, n_obstacles=8, formation="horizontal"),
    4: dict(height=50, width=50, n_obstacles=8, formation="vertical"),
}


class ConfigError(ValueError):
    """A bad configuration or scenario value; the message is one line naming the field."""


class RunFailed(RuntimeError):
    """A run that cannot go on (its learner died); the message is one line saying what is kept."""


def _fail(field_name: str, message: str) -> None:
    raise ConfigError(f"{field_name}: {message}")


@dataclass(frozen=True)
class GameConfig:
    """All rules of one game. Defaults are setting 1."""

    # the paper's named setting (1-4) whose board, obstacles and formation the others override; null: none
    setting: int | None = 1
    height: int = 25  # rows of the board
    width: int = 25  # columns of the board
    n_obstacles: int = 3  # obstacles, at most one per row of the obstacle band
    formation: str = "horizontal"  # horizontal or vertical: where the followers keep to, beside or behind the leader
    d_min: float = 1.0  # the formation holds while every follower is farther than d_min from the leader
    d_max: float = 4.0  # and nearer than d_max
    max_steps: int = 200  # steps before an episode is truncated
    n_followers: int = 1  # followers beside the leader
    # the leader's start cell; null: the rules' default for the formation and follower count (docs/GAME.md)
    leader_start: tuple[int, int] | None = None
    follower_starts: tuple[tuple[int, int], ...] | None = None  # the followers' start cells; null: the rules' default
    obstacle_speeds: tuple[int, ...] = (1, 2)  # the speeds (cells a step) an obstacle is drawn with
    # the paper's comprehensive reward, its weights as config values: each agent's when the leader reaches the
    # destination with the formation kept
    reward_reach: float = 50.0
    reward_collision: float = -1.0  # each agent's reward when it collides
    reward_formation_kept: float = 1.0  # each agent's reward for a step that keeps the formation
    reward_formation_broken: float = -1.0  # each agent's reward for a step that breaks it
    # what the agents observe: "pixels", the 84x84 RGB screen, or "grid", one plane per entity kind on the board
    obs_type: str = "pixels"
    frame_stack: int = 4  # observations stack this many frames, the newest last
    screen_size: int = field(default=84, repr=False)  # pixels of a side of the screen (not a config key)

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_setting(cls, setting: int | None = 1, **overrides: Any) -> GameConfig:
        """A named setting (1-4, or None for the plain defaults) with field overrides."""
        known = {f.name for f in dataclasses.fields(cls)}
        for key in overrides:
            if key not in known:
                _fail(key, f"unknown game config key; allowed: {', '.join(sorted(known))}")
        if setting is not None and setting not in SETTINGS:
            _fail("setting", f"unknown setting {setting!r}; allowed: 1, 2, 3, 4")
        base = dict(SETTINGS[setting]) if setting is not None else {}
        base.update(overrides)
        base["setting"] = setting
        return cls(**_normalise(base))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> GameConfig:
        values = dict(values)
        return cls.from_setting(values.pop("setting", 1), **values)

    def to_dict(self) -> dict[str, Any]:
        """Plain values that ``from_dict`` turns back into an equal config."""
        out = dataclasses.asdict(self)
        for key in ("leader_start", "follower_starts", "obstacle_speeds"):
            if out[key] is not None:
                out[key] = _plain(out[key])
        out.pop("screen_size")
        return out

    def replace(self, **changes: Any) -> GameConfig:
        return GameConfig.from_dict({**self.to_dict(), **changes})

    def variant(self, setting: int | None = None, n_followers: int | None = None) -> GameConfig:
        """The same rules on another named ``setting`` (its board, obstacles and formation) and/or with another
        number of followers, from the default starts; the rest (distances, rewards, screens) as they are. None:
        as this game has it."""
        values = {k: v for k, v in self.to_dict().items() if k not in ("leader_start", "follower_starts")}
        if setting is not None:
            for key in (*SETTINGS[1], "setting"):
                values.pop(key)
            values["setting"] = setting
        if n_followers is not None:
            values["n_followers"] = n_followers
        return GameConfig.from_dict(values)

    # ----------------------------------------------------------------- derived values
    @property
    def destination(self) -> tuple[int, int]:
        return (0, self.width // 2)

    @property
    def follower_names(self) -> list[str]:
        if self.n_followers == 1:
            return ["follower"]
        return [f"follower_{i}" for i in range(1, self.n_followers + 1)]

    @property
    def agent_names(self) -> list[str]:
        return ["leader", *self.follower_names]

    @property
    def obstacle_band(self) -> tuple[int, int]:
        """The obstacle band's rows ``[lo, hi)`` for random obstacles (docs/GAME.md, 'Entities')."""
        return (self.height // 5, self.height - self.height // 5)

    @property
    def obstacle_rows(self) -> tuple[int, ...]:
        """Rows random obstacles are drawn from: the band less the rows of agent starts and of
        the destination (on the named settings the band holds none of them: it is the band)."""
        leader, followers = self.starts
        taken = {leader[0], self.destination[0], *(f[0] for f in followers)}
        lo, hi = self.obstacle_band
        return tuple(r for r in range(lo, hi) if r not in taken)

    def default_starts(self) -> tuple[tuple[int, int], tuple[tuple[int, int], ...]]:
        """The leader's and the followers' start cells for 1-4 followers (docs/GAME.md, 'Teams of 1-4 followers'):
        every follower 2 to 2.83 cells from the leader and at least 2 from every other, inside (d_min, d_max)
        with the defaults."""
        H, W = self.height, self.width
        c0 = W // 2 - W // 5
        k = self.n_followers
        if self.formation == "horizontal":  # beside the leader, then two rows behind it
            # a third follower ahead of the leader would have to pass it before the destination row, so from
            # three followers on the leader starts two rows up and the others stand behind it
            leader = (H - 1, c0) if k <= 2 else (H - 3, c0)
            followers = {1: ((H - 1, c0 - 2),),
                         2: ((H - 1, c0 - 2), (H - 1, c0 + 2)),
                         3: ((H - 3, c0 - 2), (H - 3, c0 + 2), (H - 1, c0)),
                         4: ((H - 3, c0 - 2), (H - 3, c0 + 2), (H - 1, c0 - 2), (H - 1, c0 + 2))}
        else:  # behind the leader, two rows back, then beside it
            leader = (H - 3, c0)
            followers = {1: ((H - 1, c0),),
                         2: ((H - 1, c0 - 1), (H - 1, c0 + 1)),
                         3: ((H - 1, c0 - 2), (H - 1, c0), (H - 1, c0 + 2)),
                         4: ((H - 1, c0 - 1), (H - 1, c0 + 1), (H - 3, c0 - 2), (H - 3, c0 + 2))}
        if k not in followers:
            _fail("follower_starts", f"no default start for n_followers={k} (allowed: 1-4); give follower_starts")
        return leader, followers[k]

    @property
    def starts(self) -> tuple[tuple[int, int], tuple[tuple[int, int], ...]]:
        """(leader start, follower starts), the config's own or the default starts (docs/GAME.md, 'Entities')."""
        default_leader, default_followers = (None, None)
        if self.leader_start is None or self.follower_starts is None:
            default_leader, default_followers = self.default_starts()
        leader = self.leader_start if self.leader_start is not None else default_leader
        followers = self.follower_starts if self.follower_starts is not None else default_followers
        return leader, followers

    def formation_kept(self, distance: float) -> bool:
        return self.d_min < distance < self.d_max

    # ----------------------------------------------------------------- validation
    def __post_init__(self) -> None:
        self._check_types()
        H, W = self.height, self.width
        if self.formation not in FORMATIONS:
            _fail("formation", f"{self.formation!r} is not allowed; allowed: {', '.join(FORMATIONS)}")
        if self.obs_type not in OBS_TYPES:
            _fail("obs_type", f"{self.obs_type!r} is not allowed; allowed: {', '.join(OBS_TYPES)}")
        if not 3 <= H <= self.screen_size:
            _fail("height", f"{H} is not allowed; allowed: 3..{self.screen_size}")
        if not 3 <= W <= self.screen_size:
            _fail("width", f"{W} is not allowed; allowed: 3..{self.screen_size}")
        if not 0 <= self.d_min < self.d_max:
            _fail("d_min", f"need 0 <= d_min < d_max, got d_min={self.d_min}, d_max={self.d_max}")
        if self.max_steps < 1:
            _fail("max_steps", f"{self.max_steps} is not allowed; allowed: an integer >= 1")
        if self.n_followers < 1:
            _fail("n_followers", f"{self.n_followers} is not allowed; allowed: an integer >= 1")
        if self.frame_stack < 1:
            _fail("frame_stack", f"{self.frame_stack} is not allowed; allowed: an integer >= 1")
        if not self.obstacle_speeds or any(s < 1 for s in self.obstacle_speeds):
            _fail("obstacle_speeds", f"{list(self.obstacle_speeds)} is not allowed; "
                                     "allowed: a non-empty list of integers >= 1")
        leader, followers = self.starts
        if len(followers) != self.n_followers:
            _fail("follower_starts", f"has {len(followers)} cells but n_followers={self.n_followers}")
        names = self.agent_names
        for name, cell in zip(names, (leader, *followers)):
            if not (0 <= cell[0] < H and 0 <= cell[1] < W):
                what = "leader_start" if name == "leader" else "follower_starts"
                _fail(what, f"{name} start {list(cell)} is outside the {H}x{W} board")
        if len({tuple(c) for c in (leader, *followers)}) != len(names):
            _fail("follower_starts", "two agents start on the same cell")
        if tuple(leader) == self.destination:
            _fail("leader_start", f"the leader starts on the destination {list(self.destination)}")
        broken = formation_broken_by(self, leader, followers)
        if broken:
            _fail("follower_starts", f"the start breaks the formation: {broken}")
        free_rows = len(self.obstacle_rows)
        if not 0 <= self.n_obstacles <= free_rows:
            lo, hi = self.obstacle_band
            _fail("n_obstacles", f"{self.n_obstacles} is not allowed; allowed: 0..{free_rows} (one per row "
                                 f"of the obstacle band, rows {lo}..{hi - 1}, not counting agents' start rows)")

    def _check_types(self) -> None:
        ints = ("height", "width", "n_obstacles", "max_steps", "n_followers", "frame_stack")
        for name in ints:
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool):
                _fail(name, f"{value!r} is not allowed; allowed: an integer")
        nums = ("d_min", "d_max", "reward_reach", "reward_collision", "reward_formation_kept",
                "reward_formation_broken")
        for name in nums:
            value = getattr(self, name)
            if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
                _fail(name, f"{value!r} is not allowed; allowed: a finite number")


def formation_broken_by(config: GameConfig, leader, followers) -> str:
    """Why these cells break the formation, or '' when it is kept (docs/GAME.md, 'One step', rule 4)."""
    for i, f in enumerate(followers):
        d = math.dist(leader, f)
        if not config.formation_kept(d):
            return (f"follower {i + 1} is {d:.3g} cells from the leader; "
                    f"allowed: more than d_min={config.d_min} and less than d_max={config.d_max}")
    for i in range(len(followers)):
        for j in range(i + 1, len(followers)):
            d = math.dist(followers[i], followers[j])
            if d <= config.d_min:
                return f"followers {i + 1} and {j + 1} are {d:.3g} cells apart; allowed: more than d_min"
    return ""


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def _cell(field_name: str, value: Any) -> tuple[int, int]:
    if (not isinstance(value, list | tuple) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        _fail(field_name, f"{value!r} is not allowed; allowed: a [row, col] pair of integers")
    return (int(value[0]), int(value[1]))


def _normalise(values: dict[str, Any]) -> dict[str, Any]:
    """Turn lists from YAML or JSON into the tuples the frozen config holds."""
    out = dict(values)
    if out.get("leader_start") is not None:
        out["leader_start"] = _cell("leader_start", out["leader_start"])
    if out.get("follower_starts") is not None:
        starts = out["follower_starts"]
        if not isinstance(starts, list | tuple) or not starts:
            _fail("follower_starts", f"{starts!r} is not allowed; allowed: a list of [row, col] pairs")
        out["follower_starts"] = tuple(_cell("follower_starts", c) for c in starts)
    if "obstacle_speeds" in out:
        speeds = out["obstacle_speeds"]
        if not isinstance(speeds, list | tuple) or not all(
                isinstance(s, int) and not isinstance(s, bool) for s in speeds):
            _fail("obstacle_speeds", f"{speeds!r} is not allowed; allowed: a list of integers >= 1")
        out["obstacle_speeds"] = tuple(int(s) for s in speeds)
    return out
