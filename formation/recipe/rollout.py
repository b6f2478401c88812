"""Rollouts: a batch of games played by given actions, turned into replay records.

``GameRollout`` owns a ``BatchedGame``, keeps each game's frame stack for acting, and after
every step returns the records of that step (see ``formation.recipe.replay``): one per game, plus
a terminal record for each game whose episode was just truncated. Finished games restart at once.
Where the networks read screens per cell (``train.screen_cells``), the records hold only those
cells, the pixels the networks read: 11x less than a screen on a 25x25 board, 2.8x on 50x50, in
the pushes, the replay's memory and stacks and the learner's batches. Acting reads whole screens.
No Ray, no torch: the rollout actors (EnvRunners) and the tests use it alike.
"""

from __future__ import annotations

import numpy as np

from formation.config import GameConfig
from formation.game import BatchedGame, Observer, Scenario
from formation.game.core import MOVES
from formation.game.render import cell_pixels
from formation.recipe.replay import Chunk

STARTS = ("spec", "exploring")  # where an episode started: its statistics' "start"


def exploring_start(scenario: Scenario, config: GameConfig, rng: np.random.Generator, tries: int = 20) -> Scenario:
    """``scenario`` with its team moved as one, every agent by the same rows and columns, to a place drawn
    uniformly among those that keep every agent on the board, none within distance 1 of an obstacle
    (spec rule 3) and not on the destination; the obstacles as they were. ``scenario`` itself if
    ``tries`` draws find no such place."""
    team = np.array([scenario.leader, *scenario.followers])
    obstacles = np.array([(r, c) for r, c, _ in scenario.obstacles]).reshape(-1, 2)
    low, high = -team.min(0), np.array([config.height, config.width]) - 1 - team.max(0)
    for _ in range(tries):
        moved = team + rng.integers(low, high + 1)
        gaps = ((moved[:, None, :] - obstacles[None, :, :]) ** 2).sum(-1)
        if (gaps > 1).all() and tuple(moved[0]) != config.destination:
            cells = [tuple(int(v) for v in cell) for cell in moved]
            return Scenario(leader=cells[0], followers=tuple(cells[1:]), obstacles=scenario.obstacles)
    return scenario


class GameRollout:
    def __init__(self, config: GameConfig, batch_size: int, seed: int | None = None, stream_offset: int = 0,
                 potential=None, shaping: float = 0.0, gamma: float = 0.99, exploring_starts: float = 0.0,
                 screen_cells: bool = False, reward_formation_kept: float | None = None, team_reward: bool = False):
        """``potential`` (a ``formation.recipe.shaping.Potential``), if given, adds the shaping term
        ``shaping * (gamma * Phi(s') - Phi(s))`` to every stored reward (never to the episode
        statistics, which report the game's own reward); so do ``reward_formation_kept`` (the reward of a step
        in formation instead of the game's) and ``team_reward`` (the followers also get the reach reward).
        ``exploring_starts``: the fraction of episodes
        that start from an ``exploring_start`` instead of the spec's places. ``screen_cells`` (screens
        only): the records hold one pixel per cell of each screen, the pixels ``ScreenCells`` reads
        (``formation.game.render.cell_pixels``), instead of the whole screen."""
        if screen_cells and config.obs_type != "pixels":
            raise ValueError(f"screen_cells: only screens are read per cell, not {config.obs_type} observations")
        self.config = config
        self.potential, self.shaping, self.gamma = potential, shaping, gamma
        self.reward_formation_kept, self.team_reward = reward_formation_kept, team_reward
        self.game = BatchedGame(config, batch_size=batch_size, seed=seed)
        self.game.reset()
        self.exploring_starts = exploring_starts
        self._start_rng = np.random.default_rng([seed or 0, stream_offset, 11])
        self._starts = np.zeros(batch_size, np.int8)  # each game's episode: its index in STARTS
        self._restart(np.ones(batch_size, bool))
        self.observer = Observer(self.game)
        self.batch_size = batch_size
        self.n_agents = self.game.n_agents
        self.streams = stream_offset + np.arange(batch_size)
        everyone = np.ones(batch_size, bool)
        self.observations = self.observer.observe(everyone)  # (B, h, w, c*k), for acting
        self._cells = None  # the rows and columns of the pixels a record keeps; None: all of them
        if screen_cells:
            rows, cols = self.observer.frame_shape[:2]
            self._cells = (cell_pixels(config.height, rows), cell_pixels(config.width, cols))
        self._frames = self._recorded(self.observer.renderer.frames)  # what each game shows now
        self._first = everyone.copy()
        # Episode statistics of games that finished, since the last ``pop_episodes``.
        self._episodes: list[dict] = []
        self._returns = np.zeros((batch_size, self.n_agents))
        self._phi = potential(self.game) if potential is not None else None

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        """The shape of a record's frame (what a replay of these records stores): the observer's frame, or
        its cells (``screen_cells``)."""
        if self._cells is None:
            return tuple(self.observer.frame_shape)
        return (self.config.height, self.config.width, self.observer.frame_shape[2])

    def _recorded(self, frames: np.ndarray) -> np.ndarray:
        """A copy of rendered ``frames`` (B, h, w, c) as records keep them: whole, or their cells."""
        if self._cells is None:
            return frames.copy()
        rows, cols = self._cells
        return frames.take(rows, axis=1).take(cols, axis=2)  # a new (B, H, W, c) array, in C order

    def step(self, actions: np.ndarray, labels: np.ndarray | None = None, answers: np.ndarray | None = None,
             safe: np.ndarray | None = None) -> Chunk:
        """Play one joint action per game; return the records of this step. ``labels`` (B, 1+k):
        a teacher's action for each agent in the state before the step, -1 where there is none;
        ``answers`` (B, 1+k, moves): its action for each move the leader could make there; ``safe`` (B,): the
        joint actions that start safe steps (see ``Chunk``)."""
        g = self.game
        frames_before, first = self._frames, self._first
        g.step(actions)
        done = g.done.copy()
        rewards = g.rewards.copy()
        if self.reward_formation_kept is not None:
            rewards += (np.float32(self.reward_formation_kept - self.config.reward_formation_kept)
                        * g.formation_kept[:, None])
        if self.team_reward:
            rewards[:, 1:] += np.float32(self.config.reward_reach) * g.reached[:, None]
        if self.potential is not None:
            phi_next = self.potential(g)
            rewards += self.shaping * (self.gamma * phi_next - self._phi)
            self._phi = phi_next
        records = Chunk(streams=self.streams, frames=frames_before, first=first,
                        terminal=np.zeros(self.batch_size, bool), actions=np.asarray(actions, np.int8),
                        rewards=rewards, terminated=g.terminated.copy(), truncated=g.truncated.copy(),
                        labels=np.full(actions.shape, -1, np.int8) if labels is None else labels.astype(np.int8),
                        answers=None if answers is None else answers.astype(np.int8),
                        safe=None if safe is None else safe.astype(np.uint16))
        self._returns += g.rewards
        if done.any():
            ended = np.flatnonzero(done)
            for i in ended.tolist():
                self._episodes.append({
                    "returns": self._returns[i].tolist(), "steps": int(g.steps[i]), "success": bool(g.success[i]),
                    "collided": bool(g.collided[i].any()), "broken": bool(not g.formation_kept[i]),
                    "reached": bool(g.reached[i]), "truncated": bool(g.truncated[i]),
                    "start": STARTS[self._starts[i]]})
            self._returns[ended] = 0
            # Only a truncated episode bootstraps from the state after its last step.
            cut = np.flatnonzero(g.truncated)
            if len(cut):
                n = len(cut)
                after = self.observer.renderer.render()[cut]
                terminal = Chunk(streams=self.streams[cut], frames=self._recorded(after),
                                 first=np.zeros(n, bool), terminal=np.ones(n, bool),
                                 actions=np.zeros((n, self.n_agents), np.int8),
                                 rewards=np.zeros((n, self.n_agents), np.float32), terminated=np.zeros(n, bool),
                                 truncated=np.zeros(n, bool), labels=np.full((n, self.n_agents), -1, np.int8))
                records = concatenate([records, terminal])
            g.reset(mask=done)
            self._restart(done)
            if self.potential is not None:
                self._phi[done] = self.potential(g, done)[done]
        self.observations = self.observer.observe(done)
        self._frames = self._recorded(self.observer.renderer.frames)
        self._first = done
        return records

    def _restart(self, restarted: np.ndarray) -> None:
        """Move the team of a random ``exploring_starts`` share of the ``restarted`` games (just reset)."""
        self._starts[restarted] = STARTS.index("spec")
        if self.exploring_starts <= 0:
            return
        moved = restarted & (self._start_rng.random(len(restarted)) < self.exploring_starts)
        if moved.any():
            self.game.load([exploring_start(self.game.scenario(i), self.config, self._start_rng)
                            for i in np.flatnonzero(moved)], mask=moved)
            self._starts[moved] = STARTS.index("exploring")

    def pop_episodes(self) -> list[dict]:
        out, self._episodes = self._episodes, []
        return out


def concatenate(chunks: list[Chunk]) -> Chunk:
    """One chunk of the records of ``chunks``, in order; ``answers`` -1 and ``safe`` 0 for those without,
    None if none has."""
    fields = ("streams", "frames", "first", "terminal", "actions", "rewards", "terminated", "truncated", "labels")
    out = Chunk(**{f: np.concatenate([getattr(c, f) for c in chunks]) for f in fields})
    if any(c.answers is not None for c in chunks):
        moves = len(MOVES)
        out.answers = np.concatenate([c.answers if c.answers is not None
                                      else np.full((len(c), c.actions.shape[1], moves), -1, np.int8) for c in chunks])
    if any(c.safe is not None for c in chunks):
        out.safe = np.concatenate([c.safe if c.safe is not None else np.zeros(len(c), np.uint16) for c in chunks])
    return out
