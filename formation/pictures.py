"""Pictures for people: animated GIFs of screens and the paper's figures (Pillow). No Ray, no torch."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def upscale(frame: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement of an (H, W, 3) frame."""
    return frame.repeat(factor, axis=0).repeat(factor, axis=1)


def side_by_side(frames: list[np.ndarray], gap: int = 2) -> np.ndarray:
    """Frames of equal height joined left to right with a grey gap."""
    h = frames[0].shape[0]
    bar = np.full((h, gap, 3), 96, np.uint8)
    parts = []
    for i, f in enumerate(frames):
        if i:
            parts.append(bar)
        parts.append(f)
    return np.concatenate(parts, axis=1)


def write_gif(path: str | Path, frames: list[np.ndarray], scale: int = 4, ms_per_frame: int = 120,
              hold_last: int = 6) -> Path:
    """Write an animated GIF that loops, holding the last frame a little longer."""
    from PIL import Image

    if not frames:
        raise ValueError("write_gif: no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(upscale(np.asarray(f, np.uint8), scale)) for f in frames]
    images += [images[-1]] * hold_last
    images[0].save(path, save_all=True, append_images=images[1:], duration=ms_per_frame, loop=0,
                   optimize=False)
    return path


def write_episodes_gif(path: str | Path, episodes: list[list[np.ndarray]], **gif_options) -> Path:
    """Episodes of screens side by side in one GIF; an episode that ends early holds its last screen."""
    longest = max(len(frames) for frames in episodes)
    padded = [frames + [frames[-1]] * (longest - len(frames)) for frames in episodes]
    return write_gif(path, [side_by_side([p[t] for p in padded]) for t in range(longest)], **gif_options)


# ====================================================================== `formation render`: the paper's figures
# Layout constants: every figure's size follows from these (tests compute the expected sizes from them).
SCALE = 3  # screen enlargement in episodes.gif and q_values.png
CAPTION = 18  # height of a caption band under a panel or above a row
GAP = 2  # grey gap between panels of episodes.gif
BOARD_PX = 360  # the board of paths.png is about this wide: cell = max(MIN_CELL, BOARD_PX // max(H, W))
MIN_CELL = 6
MARGIN = 10  # around figures and between their parts
CHART_W = 190  # one agent's Q-value bar chart in q_values.png
KEY_FRAMES = 3  # rows of q_values.png
PLOT_W, PLOT_H = 460, 300  # one panel of training.png, axes and labels included
PLOT_PAD = (52, 26, 14, 40)  # left, top, right, bottom: room for tick labels, title, axis label

BACKGROUND = (255, 255, 255)
INK = (20, 20, 20)
FAINT = (200, 200, 200)
BOARD = (0, 0, 0)
GRID_LINE = (40, 40, 40)
LEADER = (0, 0, 255)  # the screen's colours (formation.game.render)
FOLLOWER = (0, 255, 0)
OBSTACLE = (255, 0, 0)
DESTINATION = (255, 255, 255)
MARK = (255, 200, 0)  # where an episode ended badly
ACTION_LABELS = ("F", "FL", "FR", "S")


def _font(size: int = 12):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the bitmap font, one size
        return ImageFont.load_default()


def agent_colour(index: int) -> tuple[int, int, int]:
    """The leader's colour for agent 0, the followers' for the others."""
    return LEADER if index == 0 else FOLLOWER


def _fade(colour: tuple[int, int, int], t: float, towards=(0, 0, 0), floor: float = 0.3) -> tuple[int, int, int]:
    """``colour`` at time fraction ``t`` in [0, 1]: early steps faded towards ``towards``, the last at full colour."""
    w = floor + (1 - floor) * max(0.0, min(1.0, t))
    return tuple(int(round(c * w + b * (1 - w))) for c, b in zip(colour, towards))


# ---------------------------------------------------------------------- episodes with their paths and Q-values
class Episode:
    """One greedy episode: per-step positions (``steps + 1`` entries, the start first), the joint actions
    and each agent's Q-values before each step, the screens, and how it ended."""

    def __init__(self, index: int, leader: list, followers: list, obstacles: list, actions: list, q: list,
                 screens: list, outcome: str, success: bool):
        self.index = index
        self.leader = leader  # [(r, c)] per time
        self.followers = followers  # [[(r, c)] per time] per follower
        self.obstacles = obstacles  # [[(r, c)] per time] per obstacle
        self.actions = actions  # [(1+k,) ints] per step
        self.q = q  # [(1+k, 4) floats] per step
        self.screens = screens  # [(84, 84, 3)] per time
        self.outcome = outcome
        self.success = success

    @property
    def steps(self) -> int:
        return len(self.actions)


def outcome_text(result: dict, i: int) -> str:
    """How episode ``i`` of ``play_greedy``'s result ended, in a few words."""
    steps = int(result["steps"][i])
    if result["success"][i]:
        return f"success in {steps} steps"
    who = [name for key, name in (("leader_collided", "leader"), ("follower_collided", "follower")) if result[key][i]]
    why = [f"{' & '.join(who)} collided"] if who else []
    why += [label for key, label in (("broken", "formation broken"), ("timeout", "time-out")) if result[key][i]]
    return f"{'; '.join(why) or 'failed'} at step {steps}"


def play_episodes(policy, episodes: int, seed: int) -> list[Episode]:
    """Greedy play of ``episodes`` scenarios of ``seed`` (``formation.evaluate.play_greedy``, as ``formation
    evaluate`` plays them), keeping each episode's global paths, Q-values and screens."""
    from formation.evaluate import play_greedy

    config = policy.game
    last_q: list[np.ndarray] = []
    actions_of: list[list[np.ndarray]] = [[] for _ in range(episodes)]
    q_of: list[list[np.ndarray]] = [[] for _ in range(episodes)]

    def act(obs: np.ndarray) -> np.ndarray:
        q = policy.q_batch(obs)  # (N, 1+k, 4)
        last_q[:] = [q]
        return q.argmax(axis=-1)

    def watch(game, actions: np.ndarray, live: np.ndarray) -> None:
        for i in np.flatnonzero(live):
            actions_of[i].append(np.array(actions[i]))
            q_of[i].append(np.array(last_q[0][i], np.float64))

    result = play_greedy(config, act, episodes, seed, record=episodes, watch=watch)
    out = []
    for i in range(episodes):
        leader, followers, obstacles = replay_positions(config, result["scenarios"][i], actions_of[i])
        out.append(Episode(i, leader, followers, obstacles, actions_of[i], q_of[i], result["screens"][i],
                           outcome_text(result, i), bool(result["success"][i])))
    return out


def replay_positions(config, scenario, actions: list) -> tuple[list, list, list]:
    """Every position of an episode (leader, followers, obstacles; the start first, the end last), replaying
    its joint actions from its scenario."""
    from formation.game import BatchedGame

    game = BatchedGame(config, batch_size=1)
    game.load([scenario])
    leader: list = []
    followers: list = [[] for _ in range(config.n_followers)]
    obstacles: list = [[] for _ in range(game.n_obstacles)]
    for t in range(len(actions) + 1):
        if t:
            game.step(np.asarray(actions[t - 1])[None, :])
        p = game.positions[0]
        leader.append((int(p[0, 0]), int(p[0, 1])))
        for j in range(config.n_followers):
            followers[j].append((int(p[1 + j, 0]), int(p[1 + j, 1])))
        for j in range(game.n_obstacles):
            obstacles[j].append((int(game.obstacle_rows[0, j]), int(game.obstacle_cols[0, j])))
    return leader, followers, obstacles


# ---------------------------------------------------------------------- 1. episodes.gif
def episode_panel_size() -> tuple[int, int]:
    """(width, height) of one panel of episodes.gif: the enlarged screen over a caption band."""
    return 84 * SCALE, 84 * SCALE + CAPTION


def episodes_gif_size(n: int) -> tuple[int, int]:
    w, h = episode_panel_size()
    return n * w + (n - 1) * GAP, h


def _captioned(screen: np.ndarray, text: str, colour=INK) -> np.ndarray:
    from PIL import Image, ImageDraw

    w, h = episode_panel_size()
    image = Image.new("RGB", (w, h), BACKGROUND)
    image.paste(Image.fromarray(upscale(np.asarray(screen, np.uint8), SCALE)), (0, 0))
    ImageDraw.Draw(image).text((4, 84 * SCALE + 3), text, fill=colour, font=_font(12))
    return np.asarray(image)


def write_render_gif(path: str | Path, episodes: list[Episode]) -> Path:
    """The episodes side by side, enlarged, each captioned with its step and, at its end, its outcome."""
    longest = max(len(e.screens) for e in episodes)
    frames = []
    for t in range(longest):
        panels = []
        for e in episodes:
            k = min(t, len(e.screens) - 1)
            if k == len(e.screens) - 1:
                text, colour = f"#{e.index}: {e.outcome}", ((0, 140, 0) if e.success else (200, 0, 0))
            else:
                text, colour = f"#{e.index}: step {k}", INK
            panels.append(_captioned(e.screens[k], text, colour))
        frames.append(side_by_side(panels, GAP))
    return write_gif(path, frames, scale=1, ms_per_frame=150, hold_last=10)


# ---------------------------------------------------------------------- 2. paths.png (paper Fig. 7)
def cell_size(config) -> int:
    return max(MIN_CELL, BOARD_PX // max(config.height, config.width))


def paths_panel_size(config) -> tuple[int, int]:
    """(width, height) of one episode's panel of paths.png: the board over a caption band."""
    c = cell_size(config)
    return config.width * c, config.height * c + CAPTION


def paths_size(config, n: int) -> tuple[int, int]:
    w, h = paths_panel_size(config)
    return 2 * MARGIN + n * w + (n - 1) * MARGIN, 2 * MARGIN + h + CAPTION


def draw_paths(config, episode: Episode):
    """One episode's board with the global paths of everyone (time fades from dark to full colour; start
    cells ringed in white, the destination a white square). Returns ``(image, centre)``: ``centre((row,
    col))`` is the pixel (x, y) of a cell's centre in the image."""
    from PIL import Image, ImageDraw

    c = cell_size(config)
    w, h = paths_panel_size(config)
    image = Image.new("RGB", (w, h), BACKGROUND)
    draw = ImageDraw.Draw(image)
    draw.rectangle([0, 0, config.width * c - 1, config.height * c - 1], fill=BOARD)
    if c >= 8:
        for k in range(1, config.width):
            draw.line([(k * c, 0), (k * c, config.height * c - 1)], fill=GRID_LINE)
        for k in range(1, config.height):
            draw.line([(0, k * c), (config.width * c - 1, k * c)], fill=GRID_LINE)

    def centre(cell) -> tuple[int, int]:
        return int(cell[1]) * c + c // 2, int(cell[0]) * c + c // 2

    dr, dc = config.destination
    draw.rectangle([dc * c, dr * c, dc * c + c - 1, dr * c + c - 1], fill=DESTINATION)
    n = max(1, len(episode.leader) - 1)
    radius = max(1, c // 5)

    def trail(cells: list, colour, line: bool) -> None:
        for t in range(len(cells)):
            x, y = centre(cells[t])
            if line and t:
                draw.line([centre(cells[t - 1]), (x, y)], fill=_fade(colour, t / n), width=max(1, c // 8))
        for t in range(len(cells)):
            x, y = centre(cells[t])
            draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=_fade(colour, t / n))

    for cells in episode.obstacles:
        trail(cells, OBSTACLE, line=False)
    for cells in episode.followers:
        trail(cells, FOLLOWER, line=True)
    trail(episode.leader, LEADER, line=True)
    # Start cells: a full-colour disc ringed in white; the end: a ring in the agent's colour (yellow on failure).
    big = max(2, c // 3)
    for cells, colour in [*((f, FOLLOWER) for f in episode.followers), (episode.leader, LEADER)]:
        x, y = centre(cells[-1])
        draw.ellipse([x - big, y - big, x + big, y + big], outline=colour if episode.success else MARK,
                     width=max(1, c // 10))
    for cells, colour in [*((f, FOLLOWER) for f in episode.followers), (episode.leader, LEADER)]:
        x, y = centre(cells[0])
        draw.ellipse([x - big - 1, y - big - 1, x + big + 1, y + big + 1], fill=colour, outline=DESTINATION)
    for cells in episode.obstacles:
        x, y = centre(cells[0])
        draw.rectangle([x - radius, y - radius, x + radius, y + radius], outline=DESTINATION)
    colour = (0, 140, 0) if episode.success else (200, 0, 0)
    draw.text((2, config.height * c + 3), f"#{episode.index}: {episode.outcome}", fill=colour, font=_font(12))
    return image, centre


def write_paths(path: str | Path, config, episodes: list[Episode]) -> Path:
    """paths.png: each episode's board with the paths, side by side, under a title and legend."""
    from PIL import Image, ImageDraw

    width, height = paths_size(config, len(episodes))
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    x = MARGIN
    legend = [("leader", LEADER), ("follower", FOLLOWER), ("obstacles", OBSTACLE), ("destination", (160, 160, 160))]
    draw.text((MARGIN, MARGIN), "global paths, dark = early, bright = late; start ringed white:", fill=INK,
              font=_font(11))
    lx = MARGIN + int(draw.textlength("global paths, dark = early, bright = late; start ringed white:",
                                      font=_font(11))) + 8
    for name, colour in legend:
        if lx + 70 > width:
            break
        draw.rectangle([lx, MARGIN + 2, lx + 8, MARGIN + 10], fill=colour, outline=INK)
        draw.text((lx + 11, MARGIN), name, fill=INK, font=_font(11))
        lx += 16 + int(draw.textlength(name, font=_font(11)))
    pw, _ = paths_panel_size(config)
    for e in episodes:
        panel, _ = draw_paths(config, e)
        image.paste(panel, (x, MARGIN + CAPTION))
        x += pw + MARGIN
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
    return path


# ---------------------------------------------------------------------- 3. q_values.png (paper Fig. 8)
def key_steps(episode: Episode) -> list[int]:
    """``KEY_FRAMES`` steps worth showing: the first, the first where an agent does not go forward, the last
    (a middle step, or a repeat, where these coincide)."""
    n = episode.steps
    if n == 0:
        return [0] * KEY_FRAMES
    turn = next((t for t, a in enumerate(episode.actions) if np.any(np.asarray(a) != 0)), None)
    chosen = [0]
    for t in (turn, n - 1, n // 2, n // 3, (2 * n) // 3):
        if t is not None and t not in chosen and len(chosen) < KEY_FRAMES:
            chosen.append(t)
    chosen += [n - 1] * (KEY_FRAMES - len(chosen))
    return sorted(chosen)


def q_values_size(n_agents: int) -> tuple[int, int]:
    row_h = CAPTION + 84 * SCALE
    width = 2 * MARGIN + 84 * SCALE + n_agents * (MARGIN + CHART_W)
    return width, 2 * MARGIN + CAPTION + KEY_FRAMES * row_h + (KEY_FRAMES - 1) * MARGIN


def _bar_chart(draw, box: tuple[int, int, int, int], q: np.ndarray, chosen: int, colour, title: str) -> None:
    x0, y0, x1, y1 = box
    font = _font(11)
    draw.rectangle(box, outline=FAINT)
    draw.text((x0 + 4, y0 + 3), title, fill=INK, font=font)
    top, bottom = y0 + 34, y1 - 32  # room for the title and values above, values and action names below
    low, high = min(0.0, float(q.min())), max(0.0, float(q.max()))
    span = (high - low) or 1.0

    def y_of(v: float) -> int:
        return int(round(bottom - (v - low) / span * (bottom - top)))

    zero = y_of(0.0)
    slot = (x1 - x0 - 8) // len(q)
    for a, value in enumerate(q):
        bx0 = x0 + 4 + a * slot + slot // 6
        bx1 = x0 + 4 + (a + 1) * slot - slot // 6
        fill = colour if a == chosen else (170, 170, 170)
        ya, yb = sorted((zero, y_of(float(value))))
        draw.rectangle([bx0, ya, bx1, max(ya + 1, yb)], fill=fill, outline=INK if a == chosen else None)
        label = f"{value:.1f}"
        lw = draw.textlength(label, font=font)
        ty = (min(ya, yb) - 13) if value >= 0 else (max(ya, yb) + 1)
        draw.text(((bx0 + bx1 - lw) / 2, ty), label, fill=INK, font=font)
        name = ACTION_LABELS[a] + (" *" if a == chosen else "")
        nw = draw.textlength(name, font=font)
        draw.text(((bx0 + bx1 - nw) / 2, y1 - 15), name, fill=INK, font=font)
    draw.line([(x0 + 2, zero), (x1 - 2, zero)], fill=INK)


def write_q_values(path: str | Path, episode: Episode, agent_names: list[str]) -> Path:
    """q_values.png: key frames of one episode, each the enlarged screen beside every agent's Q-values for
    F, FL, FR, S (the greedy choice coloured and starred)."""
    from PIL import Image, ImageDraw

    width, height = q_values_size(len(agent_names))
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    draw.text((MARGIN, MARGIN), f"episode #{episode.index}: {episode.outcome}; Q-values before each step",
              fill=INK, font=_font(12))
    y = MARGIN + CAPTION
    screen = 84 * SCALE
    for t in key_steps(episode):
        if episode.steps:
            actions, q = np.asarray(episode.actions[t]), np.asarray(episode.q[t])
            moves = ", ".join(f"{name} {ACTION_LABELS[int(a)]}" for name, a in zip(agent_names, actions))
            draw.text((MARGIN, y + 2), f"step {t}: {moves}", fill=INK, font=_font(12))
        image.paste(Image.fromarray(upscale(np.asarray(episode.screens[min(t, len(episode.screens) - 1)],
                                                       np.uint8), SCALE)), (MARGIN, y + CAPTION))
        x = MARGIN + screen + MARGIN
        for j, name in enumerate(agent_names):
            if episode.steps:
                _bar_chart(draw, (x, y + CAPTION, x + CHART_W - 1, y + CAPTION + screen - 1), q[j], int(actions[j]),
                           agent_colour(j), f"{name}: Q(s, a)")
            x += CHART_W + MARGIN
        y += CAPTION + screen + MARGIN
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
    return path


# ---------------------------------------------------------------------- 4. training.png (paper Fig. 6)
def read_metrics(path: str | Path) -> list[dict]:
    """The lines of a run's metrics.jsonl (unreadable lines skipped)."""
    import json

    rows = []
    for line in Path(path).read_text().splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("env_steps"), int | float) and np.isfinite(row["env_steps"]):
            rows.append(row)
    return rows


def nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """Round tick values covering [low, high], about ``count`` of them."""
    import math

    if high <= low:
        high = low + 1.0
    raw = (high - low) / max(1, count)
    step = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 2.5, 5, 10):
        if m * step >= raw:
            step *= m
            break
    first = math.floor(low / step) * step
    ticks, v = [], first
    while v <= high + step * 1e-9:
        ticks.append(round(v, 10))
        v += step
    if ticks[-1] < high - 0.02 * (high - low):  # a last tick a hair short of the data is kept
        ticks.append(round(v, 10))
    return ticks


def _tick_label(v: float) -> str:
    if abs(v) >= 1_000_000:
        return f"{v / 1e6:g}M"
    if abs(v) >= 1000:
        return f"{v / 1e3:g}k"
    return f"{v:g}"


def _binned(xs: list[float], ys: list[float], bins: int) -> list[tuple[float, float]]:
    """At most ``bins`` points: the mean of the points in each of ``bins`` equal spans of x (a long noisy
    series becomes a readable curve; a short one is kept as it is)."""
    if len(xs) <= bins:
        return list(zip(xs, ys))
    lo, hi = min(xs), max(xs)
    width = (hi - lo) / bins or 1.0
    sums: dict[int, list[float]] = {}
    for x, y in zip(xs, ys):
        b = min(bins - 1, int((x - lo) / width))
        acc = sums.setdefault(b, [0.0, 0.0, 0])
        acc[0] += x
        acc[1] += y
        acc[2] += 1
    return [(acc[0] / acc[2], acc[1] / acc[2]) for _, acc in sorted(sums.items())]


def training_size() -> tuple[int, int]:
    return 2 * MARGIN + 2 * PLOT_W + MARGIN, 2 * MARGIN + CAPTION + PLOT_H


def _plot(draw, origin: tuple[int, int], title: str, y_label: str, series: list, y_range=None) -> None:
    """A line plot in a PLOT_W x PLOT_H box: ``series`` of (name, colour, xs, ys, faint)."""
    font = _font(11)
    ox, oy = origin
    left, top, right, bottom = ox + PLOT_PAD[0], oy + PLOT_PAD[1], ox + PLOT_W - PLOT_PAD[2], oy + PLOT_H - PLOT_PAD[3]
    xs = [x for s in series for x in s[2]]
    ys = [y for s in series for y in s[3]]
    x_ticks = nice_ticks(min(xs, default=0.0), max(xs, default=1.0), count=6)
    y_ticks = nice_ticks(*(y_range or (min(ys, default=0.0), max(ys, default=1.0))))
    x_lo, x_hi = x_ticks[0], max(x_ticks[-1], max(xs, default=1.0))
    y_lo, y_hi = y_ticks[0], max(y_ticks[-1], max(ys, default=1.0))

    def px(x: float, y: float) -> tuple[float, float]:
        return (left + (x - x_lo) / ((x_hi - x_lo) or 1) * (right - left),
                bottom - (y - y_lo) / ((y_hi - y_lo) or 1) * (bottom - top))

    draw.text((left, oy + 6), title, fill=INK, font=_font(12))
    for v in x_ticks:
        x, _ = px(v, y_lo)
        draw.line([(x, top), (x, bottom)], fill=(235, 235, 235))
        draw.line([(x, bottom), (x, bottom + 4)], fill=INK)
        label = _tick_label(v)
        draw.text((x - draw.textlength(label, font=font) / 2, bottom + 6), label, fill=INK, font=font)
    for v in y_ticks:
        _, y = px(x_lo, v)
        draw.line([(left, y), (right, y)], fill=(235, 235, 235))
        draw.line([(left - 4, y), (left, y)], fill=INK)
        label = _tick_label(v)
        draw.text((left - 6 - draw.textlength(label, font=font), y - 6), label, fill=INK, font=font)
    draw.rectangle([left, top, right, bottom], outline=INK)
    axis = "env steps"
    draw.text(((left + right - draw.textlength(axis, font=font)) / 2, bottom + 22), axis, fill=INK, font=font)
    draw.text((ox + 4, top - 14), y_label, fill=INK, font=font)
    lx, ly = left + 6, top + 4
    for name, colour, sx, sy, faint in series:
        shade = _fade(colour, 0.0, towards=BACKGROUND, floor=0.4) if faint else colour
        points = [px(x, y) for x, y in _binned(sx, sy, max(2, (right - left) // 3))]
        if len(points) > 1:
            draw.line(points, fill=shade, width=1 if faint else 2)
        for x, y in points if len(points) < 40 else points[-1:]:
            draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=shade)
        entry = 26 + int(draw.textlength(name, font=font))
        if lx + entry > right and lx > left + 6:  # the legend wraps to a new line
            lx, ly = left + 6, ly + 14
        draw.line([(lx, ly + 6), (lx + 14, ly + 6)], fill=shade, width=2)
        draw.text((lx + 17, ly), name, fill=INK, font=font)
        lx += entry


def training_series(rows: list[dict]) -> tuple[list, list]:
    """(success series, return series) of metrics rows for ``training.png``: greedy evaluations (full colour)
    and exploration (faint)."""
    def series(key: str) -> tuple[list[float], list[float]]:
        points = [(float(r["env_steps"]), float(r[key])) for r in rows
                  if isinstance(r.get(key), int | float) and np.isfinite(r[key])]  # NaN: no episode ended
        return [p[0] for p in points], [p[1] for p in points]

    success = []
    for key, name, colour, faint in (("explore/success", "explore", (90, 90, 90), True),
                                     ("greedy/success", "greedy", INK, False)):
        xs, ys = series(key)
        if xs:
            success.append((name, colour, xs, ys, faint))
    agents = sorted({k[len("greedy/return_mean/"):] for r in rows for k in r if k.startswith("greedy/return_mean/")}
                    | {k[len("explore/return_"):] for r in rows for k in r if k.startswith("explore/return_")},
                    key=lambda a: (a != "leader", a))
    returns = []
    for j, agent in enumerate(agents):
        colour = agent_colour(0 if agent == "leader" else 1)
        if agent != "leader" and j > 1:  # several followers: darker greens
            colour = _fade(colour, 1.0 - 0.25 * (j - 1), floor=0.3)
        for key, name, faint in ((f"explore/return_{agent}", f"{agent} (explore)", True),
                                 (f"greedy/return_mean/{agent}", f"{agent} (greedy)", False)):
            xs, ys = series(key)
            if xs:
                returns.append((name, colour, xs, ys, faint))
    return success, returns


def write_training(path: str | Path, metrics: str | Path) -> Path:
    """training.png from a run's metrics.jsonl: success rate and each agent's return against env steps."""
    from PIL import Image, ImageDraw

    success, returns = training_series(read_metrics(metrics))
    width, height = training_size()
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    draw.text((MARGIN, MARGIN), f"training curves of {Path(metrics).parent.name}", fill=INK, font=_font(12))
    _plot(draw, (MARGIN, MARGIN + CAPTION), "success rate", "success", success, y_range=(0.0, 1.0))
    _plot(draw, (2 * MARGIN + PLOT_W, MARGIN + CAPTION), "return per episode", "return", returns)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
    return path


# ---------------------------------------------------------------------- all of them
def render(policy, out: str | Path, episodes: int = 4, seed: int = 0, metrics: str | Path | None = None,
           note=print) -> list[Path]:
    """``formation render``: episodes.gif, paths.png, q_values.png and, given a metrics.jsonl, training.png
    in ``out``. ``policy`` is a ``formation.policy.Policy`` (its ``game`` and ``q_batch``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    played = play_episodes(policy, episodes, seed)
    written = [write_render_gif(out / "episodes.gif", played),
               write_paths(out / "paths.png", policy.game, played)]
    # The Q-values of the first episode that shows a turn (else the first one).
    shown = next((e for e in played if any(np.any(np.asarray(a) != 0) for a in e.actions)), played[0])
    written.append(write_q_values(out / "q_values.png", shown, list(policy.game.agent_names)))
    if metrics is not None and Path(metrics).is_file():
        written.append(write_training(out / "training.png", metrics))
    else:
        note("training.png: skipped, no metrics.jsonl beside the checkpoint")
    return written
