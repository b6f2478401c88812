"""The training config: one YAML file with sections ``game``, ``train``, ``resources``, ``eval``,
``checkpoint``; validated completely before Ray starts (one-line ``ConfigError`` naming the key).

    game:      {setting: 1, obs_type: grid, frame_stack: 2}      # any GameConfig field
    train:     {gamma: 0.97, n_step: 3, shaping: 1.0, total_env_steps: 300000, ...}
    resources: {num_rollout_actors: 1, games_per_actor: 32, num_gpus_per_learner: 0}
    eval:      {every_env_steps: 25000, episodes: 200}
    checkpoint: {every_iterations: 10}
    refit:     {rounds: 2, episodes: 5000, horizon: 8}          # the refit phase after training

``--set train.gamma=0.99`` style overrides use the same dotted names.
"""

from __future__ import annotations

import ast
import copy
import dataclasses
import inspect
import json
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from formation.config import ConfigError, GameConfig

PATHS = ("formation", "stock")
EXPLORATIONS = ("independent", "joint")
FORECAST_SPEEDS = (1, 2)  # the obstacle speeds formation.recipe.qnet.ObstacleForecast reads

# options tried and not kept (docs/lab/TRAINING.md has their numbers; git history their code): a saved run's
# config.yaml or a policy card may still name one at its neutral value, which is dropped; any other value is refused
REMOVED: dict[str, tuple[tuple[Any, ...], str, str]] = {  # key: (neutral values, why, the version that removed it)
    "lr_end": ((None,), "a falling learning rate did not help", "0.2"),
    "failure_restarts": ((0, 0.0), "restarts from failures did not help", "0.2"),
    "mirror": ((False,), "mirrored batches did not help", "0.2"),
    "row_scan": ((0,), "the row scan did not help", "0.2"),
    "label_order": (("lockstep",), "the other label orders did not help; labels follow the lockstep order", "0.2"),
    "label_preference": ((0, 0.0), "the label preference did not help", "0.2"),
    "safety_priority": ((0, 0.0), "safety priorities did not help", "0.2"),
    "rollout_veto": ((False,), "the vetoed rollouts did not help", "0.2"),
    "safety_slack": ((0,), "path safety labels did not help", "0.2"),
    "tolerant_formation": ((False,), "tolerant labels did not help", "0.2"),
    "follower_labels": (("teacher",), "the responding followers' labels did not help", "0.2"),
    "any_shortest_move": (("none",), "the leader's margin towards any shortest move helped on setting 1 only and "
                          "lost on settings 2-3; the one recipe keeps the label", "0.4"),
    "followers_share_policy": ((True,), "the followers always share one network", "0.4"),
    "potential": (("distance",), "train.shaping: 0 turns the distance shaping off", "0.4"),
}


def drop_removed(section: str, values: dict[str, Any]) -> dict[str, Any]:
    """``values`` (one section of a config, or a card's network) without the removed options (``REMOVED``) that
    stand at their neutral value; one that does not is refused in one line naming it."""
    out = dict(values)
    for key in [k for k in out if k in REMOVED]:
        neutral, why, version = REMOVED[key]
        value = out.pop(key)
        if not any(value == v and type(value) is type(v) for v in neutral):
            allowed = " / ".join("null" if v is None else str(v).lower() for v in neutral)
            raise ConfigError(f"{section}.{key}: removed in {version} ({why}; docs/lab/TRAINING.md), so {value!r} is "
                              f"refused; allowed: {allowed} / absent")
    return out


@dataclass(frozen=True)
class TrainSettings:
    """How the two DQNs learn: by default from the game's reward alone (the reward-only recipe, docs/RECIPE.md);
    the optional ``teacher`` section adds the planner's labels."""

    gamma: float = 0.97  # discount factor
    n_step: int = 3  # steps of the n-step return in the double DQN target
    lr: float = 1e-3  # learning rate (Adam)
    batch_size: int = 64  # steps per learner update
    replay_capacity: int = 100_000  # steps the replay keeps (across its shards)
    # learner updates per env step, whatever the number of actors: one per 16 env steps gave each update four
    # times the fresh play of one per 4, and learnt as much per env step (docs/lab/TRAINING.md "Fewer updates per
    # env step")
    replay_ratio: float = 0.0625
    learning_starts: int = 2_000  # env steps in replay before the first update
    target_update_every: int = 100  # learner updates between target-network syncs
    epsilon_start: float = 1.0  # exploration rate at the start
    epsilon_end: float = 0.05  # exploration rate after epsilon_env_steps
    epsilon_env_steps: int = 10_000  # env steps over which the exploration rate falls linearly
    # independent: each agent explores on its own; joint: with probability epsilon the whole team
    # explores together, every follower copying the leader's random move (keeps the formation)
    exploration: str = "joint"
    # weight of the potential-based shaping towards the destination (formation.recipe.shaping); 0: the game's reward
    # alone
    shaping: float = 1.0
    # the training reward of a step that keeps the formation, in place of the game's (the paper's +1); null: the
    # game's. With the +1 the team learns to wait in formation (setting 1 from the grid: 0.0% greedy success with
    # it, 96.1% with 0). The game's own reward still scores every episode and evaluation
    reward_formation_kept: float | None = 0.0
    # the followers' training reward also gets the game's reach reward (the paper gives it to the leader alone):
    # without it the successes took 34% more steps than the planner's, with it 3-4% (setting 1 from the grid)
    team_reward: bool = True
    steps_per_sample: int = 8  # steps of all of an actor's games per push to the replay
    # exploring starts: the fraction of training episodes that start with the team, in its start formation,
    # moved to a random place on the board clear of the obstacles (formation.recipe.rollout.exploring_start),
    # so that it also learns states its own play seldom reaches (the top row beside the destination).
    # Evaluation always starts from the spec's places
    exploring_starts: float = 0.0
    # the followers' networks answer the leader: one Q-value per (leader's move, own move), and a follower
    # makes its move in the row of the move the leader makes (formation.recipe.qnet.team_q_values)
    follower_answers_leader: bool = True
    prioritized: bool = True  # prioritized replay: TD error (+ the teacher's margin loss, with a teacher)
    hidden: int = 256  # units of the dueling heads' hidden layers
    channels: tuple[int, int, int] = (32, 64, 64)  # output channels of the encoder's three convolutions
    # the Q-networks look through a window that follows the leader: cells above it, below it, and either
    # side (formation.recipe.qnet.LeaderWindow); null: the whole screen, as the paper's networks
    leader_window: tuple[int, int, int] | None = (12, 3, 10)
    # the leader's window also marks the destination, or, where it lies outside, the window's edge nearest to it
    # (formation.recipe.qnet.LeaderWindow): on the 50x50 boards the leader otherwise sees it only in its last 12
    # rows, and only 10 columns either side. Needs leader_window
    destination_compass: bool = False
    # pixels only: the Q-networks read one pixel per cell of the board from each screen (the renderer paints a
    # whole cell in one colour, so nothing is lost; formation.recipe.qnet.ScreenCells), then every cell, and the
    # replay stores only those cells; false: the screen in 4x4-pixel patches
    screen_cells: bool = True
    # the Q-networks also read a forecast of the obstacles: for every cell, whether an agent arriving there in
    # lockstep with the leader (or one to three steps later) would collide, from the obstacles' motion in the
    # last two frames and the game's rule of motion (formation.recipe.qnet.ObstacleForecast; no weights).
    # Needs grid observations or screen_cells, and frame_stack >= 2
    obstacle_forecast: bool = True
    grad_clip: float = 10.0  # global gradient norm clip
    # the team that is evaluated, kept in best/ and exported is an exponential moving average of the networks'
    # weights (Polyak averaging) with this decay per learner update (0.999: about the last 1,000 updates); it
    # smooths the swings between evaluations. Rollouts act with the networks themselves. 0: no average
    average_decay: float = 0.0
    total_env_steps: int = 300_000  # env steps to train for
    weights_every_updates: int = 50  # learner updates between weight broadcasts to rollout actors
    path: str = "formation"  # "formation": rollout actors -> replay actor -> learner; "stock": RLlib's DQN
    seed: int = 0  # seed of games, exploration and networks

    def __post_init__(self) -> None:
        _number(self, "gamma", 0.0, 1.0)
        _number(self, "lr", 0.0, 1.0, low_open=True)
        _number(self, "replay_ratio", 0.0, 64.0, low_open=True)
        _number(self, "epsilon_start", 0.0, 1.0)
        _number(self, "epsilon_end", 0.0, 1.0)
        _number(self, "shaping", 0.0, math.inf)
        _number(self, "exploring_starts", 0.0, 1.0)
        if not (isinstance(self.average_decay, int | float) and not isinstance(self.average_decay, bool)
                and 0 <= self.average_decay < 1):
            raise ConfigError(f"train.average_decay: {self.average_decay!r} is not allowed; allowed: a number in "
                              "[0, 1) (0: no average)")
        kept = self.reward_formation_kept
        number = isinstance(kept, int | float) and not isinstance(kept, bool) and math.isfinite(kept)
        if kept is not None and not number:
            raise ConfigError(f"train.reward_formation_kept: {kept!r} is not allowed; allowed: null or a number")
        _number(self, "grad_clip", 0.0, math.inf, low_open=True)
        for name in ("n_step", "batch_size", "steps_per_sample", "replay_capacity", "target_update_every", "hidden",
                     "total_env_steps", "weights_every_updates", "epsilon_env_steps"):
            _integer(self, name, 1)
        _integer(self, "learning_starts", 0)
        _integer(self, "seed", 0)
        for name in ("prioritized", "team_reward", "screen_cells", "obstacle_forecast", "follower_answers_leader",
                     "destination_compass"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"train.{name}: {getattr(self, name)!r} is not allowed; allowed: true, false")
        if self.exploration not in EXPLORATIONS:
            raise ConfigError(f"train.exploration: {self.exploration!r} is not allowed; "
                              f"allowed: {', '.join(EXPLORATIONS)}")
        if self.path not in PATHS:
            raise ConfigError(f"train.path: {self.path!r} is not allowed; allowed: {', '.join(PATHS)}")
        if self.leader_window is not None and (
                not isinstance(self.leader_window, tuple) or len(self.leader_window) != 3
                or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in self.leader_window)):
            raise ConfigError(f"train.leader_window: {self.leader_window!r} is not allowed; "
                              "allowed: null or three integers >= 0 (cells above, below, either side)")
        if self.destination_compass and self.leader_window is None:
            raise ConfigError("train.destination_compass: true needs train.leader_window other than null; "
                              "allowed: false")
        if len(self.channels) != 3 or not all(isinstance(c, int) and c >= 1 for c in self.channels):
            raise ConfigError(f"train.channels: {list(self.channels)!r} is not allowed; allowed: three integers >= 1")


@dataclass(frozen=True)
class TeacherSettings:
    """The teacher recipe (optional; a ``teacher`` section turns it on): the clairvoyant planner labels every state
    the rollouts visit with its joint action (DAgger; formation.recipe.teacher), the learners add DQfD's large-margin
    loss towards those labels, and a share of the games follow them. Needs a planner that solves the game: 1 or 2
    followers."""

    demonstrations: float = 0.5  # fraction of games that play the teacher's labels instead of the learners' moves
    margin: float = 5.0  # DQfD large-margin loss weight towards the teacher's actions (labels)
    margin_gap: float = 5.0  # DQfD's l(a_E, a): how far above every other action the teacher's Q must stand
    planner_slack: int = 6  # paths longer than the lower bound + slack count as lost
    # labels of an episode's first step (no motion on screen yet): keep a path for the most obstacle velocities
    # instead of the clairvoyant planner's choice (formation.recipe.teacher)
    robust_first_step: bool = True
    # with train.follower_answers_leader, the labels also give the followers' rows of the moves the leader did not
    # make: the teacher's answer to every move the leader could make there (formation.recipe.teacher.Teacher.answers)
    answer_every_leader_move: bool = False
    # each Q-network also learns, beside its Q-values, which of the team's 16 joint moves start this many steps
    # free of collisions and formation breaks (the planner on the game's true state labels every visited
    # state; formation.planner.surviving_first_moves_many), with a loss weighted by safety_weight; greedy play then
    # keeps to the joint moves that head judges safe (formation.policy). 0: none. Needs one follower
    safety_horizon: int = 0
    safety_weight: float = 1.0  # weight of the safety head's loss
    # the safety head reads an encoder of its own (a copy of the Q-values' layers with weights, trained by the
    # safety loss alone) instead of the Q-values' features. Needs a safety head
    safety_encoder: bool = False

    @property
    def safety_head(self) -> bool:
        """Whether the networks learn a safety head (``safety_horizon`` not 0)."""
        return self.safety_horizon != 0

    def __post_init__(self) -> None:
        _number(self, "demonstrations", 0.0, 1.0, section="teacher")
        _number(self, "margin", 0.0, math.inf, section="teacher")
        _number(self, "margin_gap", 0.0, math.inf, section="teacher")
        _number(self, "safety_weight", 0.0, math.inf, section="teacher")
        _integer(self, "planner_slack", 0, section="teacher")
        _integer(self, "safety_horizon", 0, section="teacher")
        for name in ("robust_first_step", "answer_every_leader_move", "safety_encoder"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"teacher.{name}: {getattr(self, name)!r} is not allowed; allowed: true, false")
        if self.safety_encoder and not self.safety_horizon:
            raise ConfigError("teacher.safety_encoder: true needs teacher.safety_horizon other than 0; allowed: false")


@dataclass(frozen=True)
class ResourceSettings:
    """Where the run's work goes: its rollout actors, its learner (on a CPU or a GPU) and its replay shards. Any of
    them may change when a run is resumed (``--resume --set resources.KEY=VALUE``)."""

    num_rollout_actors: int = 1  # rollout actors (Ray actors that play games); 0 on the stock path: the driver samples
    games_per_actor: int = 32  # games each rollout actor plays at once
    cpus_per_rollout_actor: float = 1.0  # CPUs Ray reserves for each rollout actor
    num_gpus_per_learner: float = 0.0  # GPUs for each learner (0: it runs on a CPU)
    # data-parallel learners (RLlib's LearnerGroup: torch DDP, gloo on CPU, NCCL on GPU); each pulls
    # train.batch_size / num_learners records per update from its own replay shards
    num_learners: int = 1
    # replay actors the steps are spread over; each asks Ray for the memory it takes, and they spread over the nodes
    num_replay_shards: int = 1
    # on a Ray cluster that the run joins (`ray job submit`): how long to wait for the asked
    # resources to join (worker nodes still starting) before failing; a local Ray never waits
    wait_for_resources_s: float = 120.0

    def __post_init__(self) -> None:
        _number(self, "wait_for_resources_s", 0.0, 3600.0, section="resources")
        _integer(self, "num_rollout_actors", 0, section="resources")
        _integer(self, "games_per_actor", 1, section="resources")
        _integer(self, "num_replay_shards", 1, section="resources")
        _integer(self, "num_learners", 1, section="resources")
        if self.num_replay_shards < self.num_learners:
            raise ConfigError(f"resources.num_replay_shards: {self.num_replay_shards} is not allowed with "
                              f"num_learners: {self.num_learners} (each learner pulls from shards of its own); "
                              f"allowed: {self.num_learners} or more")
        _number(self, "cpus_per_rollout_actor", 0.0, 1024.0, section="resources", low_open=True)
        _number(self, "num_gpus_per_learner", 0.0, 64.0, section="resources")


@dataclass(frozen=True)
class EvalSettings:
    """The greedy evaluations during training, on held-out scenarios (``result["evaluation"]``, ``metrics.jsonl``),
    and the final one (``result.json``, ``greedy.gif``)."""

    every_env_steps: int = 25_000  # env steps between greedy evaluations during training
    episodes: int = 200  # games of each greedy evaluation
    seed: int = 1_000_000  # evaluation scenarios come from seeds training never uses
    gif_episodes: int = 3  # the final evaluation's first episodes, side by side, in the run folder's greedy.gif

    def __post_init__(self) -> None:
        _integer(self, "every_env_steps", 1, section="eval")
        _integer(self, "episodes", 1, section="eval")
        _integer(self, "seed", 0, section="eval")
        _integer(self, "gif_episodes", 0, section="eval")
        if self.gif_episodes > self.episodes:
            raise ConfigError(f"eval.gif_episodes: {self.gif_episodes} is not allowed; "
                              f"allowed: 0 to eval.episodes ({self.episodes})")


@dataclass(frozen=True)
class RefitSettings:
    """The refit phase that ends ``formation train`` when ``rounds`` > 0, and ``formation refit``: the safety
    heads of a trained team fitted again on many fresh states of its own play, labelled by the planner
    (formation.recipe.safety_refit; docs/lab/TRAINING.md "Refitting the safety heads"). Each round plays
    ``episodes`` games with the team as it is (vetoed greedy, a random joint move in an ``epsilon`` share of the
    steps), labels every state with the joint moves that start ``horizon`` steps free of collisions and
    formation breaks, and fits the heads alone (and their own encoders) for ``epochs`` passes over every state
    gathered so far; the Q-values do not change. The refitted team's veto then keeps to the joint moves the
    heads judge safe with a probability above ``veto_threshold``, and where none is, to those ``veto_fallback``
    names (``formation.policy.within_veto``)."""

    rounds: int = 0  # rounds of play, label and fit; 0: formation train ends without a refit phase
    episodes: int = 5_000  # games per round
    epsilon: float = 0.03  # share of the steps the refit's games play a random joint move
    horizon: int = 8  # the heads learn which joint moves start this many safe steps
    epochs: float = 3.0  # passes over every state gathered so far, each round
    lr: float = 3e-4  # learning rate of the heads' updates (Adam)
    batch_size: int = 256  # states per update of the heads
    holdout_episodes: int = 300  # games whose states only measure the heads' wrong verdicts
    # the refit's games come from seeds seed, seed + 1, ... (1000 games each); evaluations use 1e6, 2e6, 3e6
    seed: int = 10_000_000
    workers: int = 0  # processes that run the planner's labels (0: one per CPU core)
    veto_threshold: float = 0.97  # the refitted team's veto keeps to joint moves judged safe above this probability
    veto_fallback: str = "most_probable"  # or "above_half", the rule before it

    def __post_init__(self) -> None:
        _number(self, "veto_threshold", 0.0, 0.999, section="refit")
        if self.veto_fallback not in VETO_FALLBACKS:
            raise ConfigError(f"refit.veto_fallback: {self.veto_fallback!r} is not allowed; allowed: "
                              f"{', '.join(VETO_FALLBACKS)}")
        for name, low in (("rounds", 0), ("episodes", 1), ("horizon", 1), ("batch_size", 1),
                          ("holdout_episodes", 0), ("seed", 0), ("workers", 0)):
            _integer(self, name, low, section="refit")
        _number(self, "epsilon", 0.0, 1.0, section="refit")
        _number(self, "epochs", 0.0, 1000.0, section="refit", low_open=True)
        _number(self, "lr", 0.0, 1.0, section="refit", low_open=True)
        parts = math.ceil(self.episodes / REFIT_GAMES_PER_SEED) * self.rounds  # the seeds of its games
        first = self.seed - math.ceil(self.holdout_episodes / REFIT_GAMES_PER_SEED)  # the held-out games' seeds
        if any(first <= s < self.seed + parts for s in EVALUATION_SEEDS):
            raise ConfigError(f"refit.seed: {self.seed} is not allowed; its games would use seeds {first}.."
                              f"{self.seed + parts - 1}, which hold the evaluations' scenarios "
                              f"({', '.join(map(str, EVALUATION_SEEDS))}); allowed: a seed whose range avoids them, "
                              f"e.g. 10000000")


# where no joint move is above the veto's threshold, it keeps to those above one half (and where none is, to all),
# or to the most probably safe (formation.policy.within_veto); cards without ``veto_fallback`` read as the first,
# the rule before there was a choice
VETO_FALLBACKS = ("above_half", "most_probable")
REFIT_GAMES_PER_SEED = 1000  # a refit plays its games in parts of this many, each from a seed of its own
# the scenario seeds of training's evaluations (eval.seed), the test scenarios and the validation scenarios
EVALUATION_SEEDS = (EvalSettings.seed, 2_000_000, 3_000_000)


@dataclass(frozen=True)
class CheckpointSettings:
    """How often the run folder's ``checkpoint/`` is written (also at the end, and on Ctrl-C or SIGTERM)."""

    every_iterations: int = 10  # training iterations between checkpoints

    def __post_init__(self) -> None:
        _integer(self, "every_iterations", 1, section="checkpoint")


@dataclass(frozen=True)
class GamesSettings:
    """One team for many games (optional; a ``games`` section turns it on): the leader network and the follower
    network play every named setting of ``settings`` with every team size of ``followers`` at once, each game
    from the ``game`` section's other rules. The followers' network has a role for each follower of the largest
    team. Trains with ``formation train CONFIG --no-ray``."""

    settings: tuple[int, ...] = (1, 2, 3, 4)  # the named settings played
    followers: tuple[int, ...] = (1, 2, 3)  # the team sizes played on each

    def __post_init__(self) -> None:
        for name, allowed in (("settings", (1, 2, 3, 4)), ("followers", (1, 2, 3, 4))):
            values = getattr(self, name)
            if not (isinstance(values, tuple) and values and len(set(values)) == len(values)
                    and all(v in allowed for v in values)):
                raise ConfigError(f"games.{name}: {list(values) if isinstance(values, tuple) else values!r} is not "
                                  f"allowed; allowed: a list of distinct values from {', '.join(map(str, allowed))}")


SECTIONS = {"train": TrainSettings, "resources": ResourceSettings, "eval": EvalSettings,
            "checkpoint": CheckpointSettings, "refit": RefitSettings}
OPTIONAL_SECTIONS = {"teacher": TeacherSettings, "games": GamesSettings}  # absent: off
# what train.path: stock needs: RLlib's DQN has none of the recipe's rewards, priorities or answering followers
STOCK_TRAIN = {"shaping": 0.0, "prioritized": False, "follower_answers_leader": False, "reward_formation_kept": None,
               "team_reward": False, "average_decay": 0.0}
PLANNER_FOLLOWERS = (1, 2)  # the team sizes whose joint moves the planner searches (formation.planner)


@dataclass(frozen=True)
class RunConfig:
    game: GameConfig = field(default_factory=GameConfig)
    train: TrainSettings = field(default_factory=TrainSettings)
    resources: ResourceSettings = field(default_factory=ResourceSettings)
    eval: EvalSettings = field(default_factory=EvalSettings)
    checkpoint: CheckpointSettings = field(default_factory=CheckpointSettings)
    refit: RefitSettings = field(default_factory=RefitSettings)
    teacher: TeacherSettings | None = None  # None: the reward-only recipe
    games: GamesSettings | None = None  # None: the team plays ``game`` alone

    def __post_init__(self) -> None:
        if self.games is not None:
            for name, on in (("teacher", self.teacher is not None), ("refit.rounds", self.refit.rounds > 0),
                             ("train.path: stock", self.train.path == "stock")):
                if on:
                    raise ConfigError(f"games: a team of many games trains from the reward alone with the recipe's "
                                      f"path; allowed: no {name}")
            if self.train.leader_window is None or (self.game.obs_type == "pixels" and not self.train.screen_cells):
                raise ConfigError("games: every board is read alike only through the leader's window, cell by cell; "
                                  "allowed: train.leader_window set, and train.screen_cells: true on pixels")
        patches = self.game.obs_type == "pixels" and not self.train.screen_cells
        teacher = self.teacher
        if teacher is not None and self.game.n_followers not in PLANNER_FOLLOWERS:
            raise ConfigError(f"teacher: the planner solves teams of {' or '.join(map(str, PLANNER_FOLLOWERS))} "
                              f"followers, not game.n_followers: {self.game.n_followers}; allowed: no teacher "
                              "section (the reward-only recipe)")
        if self.refit.rounds and self.game.n_followers != 1:
            raise ConfigError(f"refit.rounds: {self.refit.rounds} needs game.n_followers: 1 "
                              f"(not {self.game.n_followers}); allowed: 0")
        if teacher is not None and teacher.safety_horizon and self.game.n_followers != 1:
            raise ConfigError(f"teacher.safety_horizon: {teacher.safety_horizon} needs game.n_followers: 1 "
                              f"(not {self.game.n_followers}); allowed: 0")
        if teacher is not None and teacher.answer_every_leader_move and not self.train.follower_answers_leader:
            raise ConfigError("teacher.answer_every_leader_move: true needs train.follower_answers_leader: true; "
                              "allowed: false")
        t = self.train
        if t.batch_size % self.resources.num_learners:
            raise ConfigError(f"train.batch_size: {t.batch_size} does not split over resources.num_learners: "
                              f"{self.resources.num_learners}; allowed: a multiple of {self.resources.num_learners}")
        res = self.resources
        if t.path == "formation" and 0 < res.num_rollout_actors < res.num_replay_shards:
            # an actor's records stack frames of its earlier ones: it fills one shard only
            raise ConfigError(f"resources.num_replay_shards: {res.num_replay_shards} is not allowed with "
                              f"num_rollout_actors: {res.num_rollout_actors} (each shard is filled by actors of its "
                              f"own); allowed: 1 to {res.num_rollout_actors}")
        if t.path == "stock" and self.resources.num_learners != 1:
            raise ConfigError(f"resources.num_learners: {self.resources.num_learners} is not allowed with "
                              "train.path: stock; allowed: 1")
        if t.path == "stock" and (teacher is not None or any(getattr(t, k) != v for k, v in STOCK_TRAIN.items())):
            needed = ", ".join(f"{k}: {json.dumps(v)}" for k, v in STOCK_TRAIN.items())
            raise ConfigError(f"train.path: stock runs RLlib's DQN on the paper's reward alone; set train.{needed}, "
                              "and no teacher section")
        if self.train.obstacle_forecast:
            if patches:
                raise ConfigError("train.obstacle_forecast: true needs the screen read per cell; allowed: false, "
                                  "or true with train.screen_cells: true or game.obs_type: grid")
            if self.game.frame_stack < 2:
                raise ConfigError(f"train.obstacle_forecast: true needs two frames to see the obstacles move; "
                                  f"allowed: false, or true with game.frame_stack >= 2 (not {self.game.frame_stack})")
            if not set(self.game.obstacle_speeds) <= set(FORECAST_SPEEDS):
                raise ConfigError(f"train.obstacle_forecast: true knows obstacle speeds {list(FORECAST_SPEEDS)} "
                                  f"(the spec's); allowed: false, or true with game.obstacle_speeds within those "
                                  f"(not {list(self.game.obstacle_speeds)})")

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> RunConfig:
        if not isinstance(values, dict):
            raise ConfigError(f"config: a mapping of sections is needed, got {type(values).__name__}")
        allowed = ("game", *SECTIONS, *OPTIONAL_SECTIONS)
        for key in values:
            if key not in allowed:
                raise ConfigError(f"{key}: unknown section; allowed: {', '.join(allowed)}")
        game_values = values.get("game") or {}
        if not isinstance(game_values, dict):
            raise ConfigError("game: a mapping of game config fields is needed")
        try:
            game = GameConfig.from_dict(game_values)
        except ConfigError as err:
            raise ConfigError(f"game.{err}") from None
        except TypeError as err:
            raise ConfigError(f"game: {err}") from None
        parts = {"game": game}
        for name in SECTIONS:
            parts[name] = section_of(name, values.get(name))
        for name in OPTIONAL_SECTIONS:  # present, even empty: on
            if name in values:
                parts[name] = section_of(name, values[name])
        return cls(**parts)

    @classmethod
    def load(cls, path: str | Path, overrides: dict[str, Any] | None = None) -> RunConfig:
        return cls.from_dict(apply_overrides(_read_yaml(path), overrides or {}))

    @classmethod
    def load_saved(cls, path: str | Path, overrides: dict[str, Any] | None = None) -> RunConfig:
        """A run folder's ``config.yaml``: as ``load``, but a key the config gained after the run was
        written takes the value that run trained with (``LATER_KEYS``), not today's default."""
        return cls.from_saved(_read_yaml(path), overrides)

    @classmethod
    def from_saved(cls, values: dict[str, Any], overrides: dict[str, Any] | None = None) -> RunConfig:
        """``load_saved`` of a config's values (a policy card's ``training.config``)."""
        values = _teacher_of_old(copy.deepcopy(values))
        for (section, key), value in LATER_KEYS.items():
            if isinstance(values.get(section), dict) and key not in values[section]:
                values[section][key] = value
        return cls.from_dict(apply_overrides(values, overrides or {}))

    @property
    def planner_options(self) -> list[str]:
        """The options with which the clairvoyant planner plays or labels while this run trains (the teacher's
        games and labels, the safety heads' labels, the refit phase); none: it learns from the reward alone."""
        teacher = self.teacher
        used = {"teacher": teacher is not None,
                "teacher.demonstrations": teacher is not None and teacher.demonstrations > 0,
                "teacher.safety_horizon": teacher is not None and teacher.safety_head,
                "refit.rounds": self.refit.rounds > 0}
        return [name for name, on in used.items() if on]

    @property
    def safety_head(self) -> bool:
        """Whether the networks learn a safety head (``teacher.safety_horizon`` not 0)."""
        return self.teacher is not None and self.teacher.safety_head

    def to_dict(self) -> dict[str, Any]:
        out = {"game": self.game.to_dict()}
        for name in SECTIONS:
            out[name] = _plain(getattr(self, name))
        for name in OPTIONAL_SECTIONS:
            if getattr(self, name) is not None:
                out[name] = _plain(getattr(self, name))
        return out

    def kinds(self) -> list[RunConfig]:
        """The run of each game the team plays: with a ``games`` section, one per (setting, followers), each with
        the ``game`` section's other rules; else this run alone."""
        if self.games is None:
            return [self]
        return [dataclasses.replace(self, game=self.game.variant(setting, k))
                for setting in self.games.settings for k in self.games.followers]


def _plain(section: Any) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(section).items()}


# the teacher's keys as configs before 0.4 held them in train:, with train.dagger turning the teacher on
OLD_TEACHER_KEYS = ("dagger", "demonstrations", "margin", "margin_gap", "planner_slack", "robust_first_step",
                    "answer_every_leader_move", "safety_horizon", "safety_weight", "safety_encoder")


def _teacher_of_old(values: dict[str, Any]) -> dict[str, Any]:
    """A saved config from before 0.4 as today's: its teacher's keys move from ``train`` to ``teacher`` (where
    ``train.dagger`` was on, the old default), ``train.potential: none`` becomes ``train.shaping: 0``."""
    train = values.get("train")
    if not isinstance(train, dict) or "teacher" in values:
        return values
    if train.get("potential") == "none":
        train.pop("potential")
        train["shaping"] = 0.0
    old = {key: train.pop(key) for key in OLD_TEACHER_KEYS if key in train}
    if not old:
        return values
    if old.pop("dagger", True):
        values["teacher"] = old
    elif old.get("demonstrations", 0.5) or old.get("safety_horizon", 0):
        raise ConfigError("train.dagger: false with train.demonstrations or train.safety_horizon: removed in 0.4 "
                          "(the teacher always labels); allowed: train.dagger: true, or both 0")
    return values


def section_of(name: str, values: dict[str, Any] | None) -> Any:
    """One section of a config (``SECTIONS[name]``) from its mapping; an unknown key is a one-line error."""
    kind = {**SECTIONS, **OPTIONAL_SECTIONS}[name]
    values = values or {}
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: a mapping is needed, got {values!r}")
    values = drop_removed(name, values)
    known = {f.name for f in dataclasses.fields(kind)}
    for key in values:
        if name == "train" and key in OLD_TEACHER_KEYS:  # a config of before 0.4
            where = "a teacher section turns it on" if key == "dagger" else f"it is teacher.{key}"
            raise ConfigError(f"train.{key}: moved to the teacher section in 0.4 ({where}); allowed: "
                              f"{', '.join(sorted(known))}")
        if key not in known:
            raise ConfigError(f"{name}.{key}: unknown key; allowed: {', '.join(sorted(known))}")
    return kind(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


# keys added to the config after runs were saved without them, with the value those runs trained with
LATER_KEYS: dict[tuple[str, str], Any] = {("train", "leader_window"): None, ("train", "screen_cells"): False,
                                          ("train", "obstacle_forecast"): False,
                                          ("train", "follower_answers_leader"): False,
                                          ("train", "reward_formation_kept"): None, ("train", "team_reward"): False,
                                          ("teacher", "answer_every_leader_move"): False}


class _YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but ``3e-4`` and ``1e5`` are numbers (YAML 1.2), not strings (YAML 1.1)."""


_YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)[eE][-+]?\d+$"),
                                  list("-+.0123456789"))


def yaml_value(text: str) -> Any:
    """The value of a YAML document (a config file, or one ``--set`` value), numbers in exponent
    notation included."""
    return yaml.load(text, Loader=_YamlLoader)


def _read_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config: no such file {str(path)!r}")
    try:
        values = yaml_value(path.read_text()) or {}
    except yaml.YAMLError as err:
        line = getattr(getattr(err, "problem_mark", None), "line", None)
        where = f" at line {line + 1}" if line is not None else ""
        raise ConfigError(f"config: {path} is not valid YAML{where}") from None
    return values


def apply_overrides(values: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """Apply ``{"train.gamma": 0.99}``-style overrides to a nested config dict (a copy)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in values.items()}
    for dotted, value in overrides.items():
        section, sep, key = dotted.partition(".")
        if not sep or not key:
            raise ConfigError(f"--set {dotted}: use section.key=value, e.g. train.gamma=0.99")
        target = out.setdefault(section, {})
        if not isinstance(target, dict):
            raise ConfigError(f"--set {dotted}: section {section!r} is not a mapping")
        target[key] = value
    return out


def _integer(obj, name: str, low: int, section: str = "train", also: str | None = None) -> None:
    value = getattr(obj, name)
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        allowed = f"an integer >= {low}" + (f" or {also}" if also else "")
        raise ConfigError(f"{section}.{name}: {value!r} is not allowed; allowed: {allowed}")


def _number(obj, name: str, low: float, high: float, section: str = "train", low_open: bool = False) -> None:
    value = getattr(obj, name)
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (low < value if low_open else low <= value) and value <= high
    if not ok:
        bound = "(" if low_open else "["
        raise ConfigError(f"{section}.{name}: {value!r} is not allowed; allowed: a number in {bound}{low}, {high}]")


# ---------------------------------------------------------------------- docs/CONFIG.md
def field_docs(cls: type) -> dict[str, str]:
    """Each field's doc: the comment lines right above its line in ``cls``'s source and the comment at its end."""
    lines, _ = inspect.getsourcelines(cls)  # a top-level class, its decorator first
    body = next(node for node in ast.parse("".join(lines)).body if isinstance(node, ast.ClassDef)).body
    docs = {}
    for node in body:
        if not isinstance(node, ast.AnnAssign):
            continue
        i = node.lineno - 1
        above = []
        while i - 1 - len(above) >= 0 and lines[i - 1 - len(above)].strip().startswith("#"):
            above.insert(0, lines[i - 1 - len(above)].strip().lstrip("#").strip())
        inline = lines[i].split("  # ", 1)[1].strip() if "  # " in lines[i] else ""
        docs[node.target.id] = " ".join(above + ([inline] if inline else []))
    return docs


def markdown() -> str:
    """docs/CONFIG.md: every option of every section, its default and its doc (``field_docs``)."""
    sections = {"game": GameConfig, **SECTIONS, **OPTIONAL_SECTIONS}
    defaults = {**RunConfig().to_dict(), **{name: _plain(kind()) for name, kind in OPTIONAL_SECTIONS.items()}}
    out = ["# Configuration", "",
           "Every option of a training config (`formation train CONFIG`), by section, with its default and meaning. "
           "`--set section.key=value` overrides one. Generated from the config's own field docs by "
           "`python -m formation.recipe.config --markdown > docs/CONFIG.md` (tests/test_config_doc.py keeps it in "
           "sync); the configs in `configs/` cite the measurement behind each value they change.", ""]
    for name, kind in sections.items():
        doc = " ".join((kind.__doc__ or "").split())
        out += [f"## {name}", "", doc, "", "| option | default | meaning |", "|---|---|---|"]
        docs = field_docs(kind)
        for key, value in defaults[name].items():
            meaning = docs[key].replace("|", "\\|")
            out.append(f"| `{key}` | `{json.dumps(value)}` | {meaning} |")
        out.append("")
    out += ["## removed", "", "Options removed (tried, not better: docs/lab/TRAINING.md). A saved run or a "
            "policy card that names one at its neutral value loads without it; any other value is refused.", "",
            "| option | neutral value | why | removed in |", "|---|---|---|---|"]
    for key, (neutral, why, version) in REMOVED.items():
        out.append(f"| `{key}` | `{json.dumps(neutral[0])}` | {why} | {version} |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    if sys.argv[1:] != ["--markdown"]:
        sys.exit("usage: python -m formation.recipe.config --markdown > docs/CONFIG.md")
    sys.stdout.write(markdown())
