"""The ``formation`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from formation.config import ConfigError, GameConfig, RunFailed
from formation.recipe.config import VETO_FALLBACKS, yaml_value
from formation.storage import (
    check_new_folder,
    check_outside,
    check_writable,
    is_uri,
    local_run_folder,
    write_text_whole,
    writing_folder,
    writing_into,
)

CHECKPOINT_HELP = "a run folder (or its storage URI), its checkpoint/ folder, or a `formation export` folder"


def counts(text: str) -> list[int]:
    """Comma-separated whole numbers above 0, as an argparse type (the benchmarks' lists of sizes)."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: allowed: whole numbers above 0, comma-separated")
    return values


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """``key=value`` strings with YAML values (``d_max=5``, ``obs_type=grid``, ``leader_start=[9,3]``)."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set: {pair!r} is not allowed; allowed: key=value")
        out[key.strip()] = yaml_value(value)
    return out


def cmd_show(args: argparse.Namespace) -> int:
    """Plan the best path of one random scenario with the planner and write it as a GIF."""
    from formation.env import FormationParallelEnv
    from formation.pictures import write_episodes_gif
    from formation.planner import shortest_path

    overrides = parse_overrides(args.set)
    config = GameConfig.from_setting(args.setting, **overrides)
    out = _picture_folder(args.out)
    frames_per_episode = []
    for seed in range(args.seed, args.seed + args.episodes):
        env = FormationParallelEnv(config)
        env.reset(seed=seed)
        scenario = env.scenario()
        path = shortest_path(scenario, config=config)
        frames = [env.screen()]
        if path is None:
            print(f"seed {seed}: no successful path within {config.max_steps} steps")
        else:
            info = {}
            for joint in path:
                _, _, _, _, info = env.step(dict(zip(env.possible_agents, joint)))
                frames.append(env.screen())
            ok = info["leader"]["success"]
            print(f"seed {seed}: planner path of {len(path)} steps, replayed: {'success' if ok else 'FAILED'}")
        frames_per_episode.append(frames)
    name = f"setting{args.setting}_planner.gif"
    with writing_into(out) as folder:  # a GIF of the same name, drawn before, is replaced whole
        write_episodes_gif(folder / name, frames_per_episode)
    print(f"wrote {out / name}")
    return 0


def _picture_folder(given: str) -> Path:
    """``--out`` of the commands that draw: a folder, new or not, that can be written."""
    out = check_writable(given, "--out")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: {given!r} is a file; allowed: a folder (new, or one to draw into)")
    return out


def cmd_train(args: argparse.Namespace) -> int:
    """Train from a config; checkpoints and metrics go to --out."""
    from formation.recipe.loop import CHECKPOINT as LOOP_CHECKPOINT
    from formation.train import train

    if args.no_ray:
        return _train_without_ray(args)
    out = None if is_uri(args.out or "") else _run_folder(args)
    if args.resume and out is not None and (out / LOOP_CHECKPOINT).is_file():
        raise ConfigError(f"--resume: {str(out)!r} holds a run trained with --no-ray; allowed: formation train "
                          f"--no-ray --resume --out {out}")
    if not args.resume and out is not None:
        _check_new_run_folder(out, ray=True)
    try:
        train(args.config, args.out, resume=args.resume, overrides=parse_overrides(args.set))
    except KeyboardInterrupt:
        return 130
    return 0


def _train_without_ray(args: argparse.Namespace) -> int:
    """``formation train --no-ray``: the recipe's single-process loop (``formation.recipe.loop``)."""
    from formation.recipe.config import RunConfig
    from formation.recipe.loop import CHECKPOINT as LOOP_CHECKPOINT
    from formation.recipe.loop import train
    from formation.train import code_commit, hardware, now, resumed_config

    if is_uri(args.out or ""):
        raise ConfigError(f"--out: {args.out!r}: a --no-ray run writes a local folder; allowed: a local path")
    out = _run_folder(args)
    if args.resume:
        if out is None:
            raise ConfigError("--resume: give the run's folder, --out DIR")
        if not (out / LOOP_CHECKPOINT).is_file() or not (out / "config.yaml").is_file():
            raise ConfigError(f"--resume: no --no-ray checkpoint to resume in {str(out)!r} (expected "
                              f"{str(out / LOOP_CHECKPOINT)!r}); train without --resume first, or resume a Ray run "
                              "without --no-ray")
        run = resumed_config(out / "config.yaml", parse_overrides(args.set))
    else:
        if args.config is None:
            raise ConfigError("config: give a config file, e.g. configs/quickstart.yaml")
        run = RunConfig.load(args.config, parse_overrides(args.set))
        out = _check_new_run_folder(out, ray=False)
    try:
        record = {"started": now(), "hardware": hardware(), "commit": code_commit()}
        summary = train(run, out, say=lambda line: print(line, flush=True), record=record, resume=args.resume)
    except KeyboardInterrupt:
        return 130
    games = summary.get("games")
    held = f"{summary['episodes']} held-out scenarios" if games is None else \
        f"{run.eval.episodes} held-out scenarios of each of {len(games)} games (their mean)"
    print(f"greedy success {summary['success']:.1%} on {held}; run folder {out}")
    return 0


def _run_folder(args: argparse.Namespace) -> Path | None:
    """The run's folder: --out, else runs/<config name> (None without either)."""
    if args.out:
        return Path(args.out)
    return Path("runs") / Path(args.config).stem if args.config else None


def _check_new_run_folder(out: Path, ray: bool) -> Path:
    """A new run goes into a new or empty folder. One that holds a Ray run's checkpoint is ``formation.train``'s
    to refuse (it says to resume), one that holds a ``--no-ray`` run's is refused here alike, and one that holds
    anything else is refused too."""
    from formation.recipe.loop import CHECKPOINT as LOOP_CHECKPOINT

    if (out / LOOP_CHECKPOINT).is_file():
        raise ConfigError(f"--out: {str(out)!r} already holds a run; use --resume to continue it or choose another "
                          "--out")
    if ray and out.is_dir() and any(p.name.startswith("checkpoint") and p.is_dir() for p in out.iterdir()):
        return check_writable(out, "--out")
    return check_new_folder(out, "--out")


def _source(path: str | Path) -> str | Path:
    """The folder a checkpoint argument reads from: an export's, or a run's (also for its checkpoint/)."""
    if is_uri(path):
        return path
    path = Path(path)
    if path.name == "checkpoint" and (path.parent / "config.yaml").is_file():
        return path.parent
    return path


def cmd_export(args: argparse.Namespace) -> int:
    """Write a checkpoint's networks and a policy card that torch alone can load."""
    from formation.policy import CARD, export, load

    if args.veto_threshold is not None:
        _veto_threshold(args.veto_threshold)
    out = check_new_folder(args.dir, "dir", source=_source(args.checkpoint))
    path = local_run_folder(args.checkpoint)
    check_outside(out, _source(path), "dir", given=args.checkpoint)
    policy = load(path)
    if args.veto_threshold is not None:
        policy = policy.with_veto_threshold(args.veto_threshold)
    if args.veto_fallback is not None:
        policy = policy.with_veto_fallback(args.veto_fallback)
    with writing_folder(out) as folder:  # the export appears whole or not at all
        export(policy, folder, half=args.half)
    print(f"exported {', '.join(sorted(policy.networks))} from {args.checkpoint} to {out} ({CARD})")
    return 0


def cmd_refit(args: argparse.Namespace) -> int:
    """Refit a trained team's safety heads on fresh states of its own play; write the team as an export."""
    from formation.policy import CARD, export, load
    from formation.recipe.config import RunConfig, section_of
    from formation.recipe.safety_refit import check_refittable
    from formation.train import refit_recorded

    overrides = parse_overrides(args.set)
    for key in overrides:
        if key.partition(".")[0] != "refit":
            raise ConfigError(f"--set {key}: refit takes refit.* keys only, e.g. --set refit.rounds=3")
    out = check_new_folder(args.dir, "dir", source=_source(args.checkpoint))
    path = local_run_folder(args.checkpoint)
    check_outside(out, _source(path), "dir", given=args.checkpoint)
    policy = load(path)
    check_refittable(policy, args.checkpoint)
    saved = path / "config.yaml"  # a run folder's refit section; an export's: the defaults
    values = RunConfig.load_saved(saved).to_dict()["refit"] if saved.is_file() else {}
    settings = section_of("refit", {**values, **{k.partition(".")[2]: v for k, v in overrides.items()}})
    if not settings.rounds:
        raise ConfigError(f"refit.rounds: 0 ({args.checkpoint} names no refit phase); allowed: --set refit.rounds=N "
                          "with N >= 1")
    print(f"refitting the safety heads of {args.checkpoint}: {settings.rounds} round(s) of {settings.episodes:,} "
          f"games, labels over {settings.horizon} steps, planner workers: {settings.workers or 'one per core'}",
          flush=True)
    # a refit of a refitted team keeps the earlier report on its card
    report = refit_recorded(policy, settings, say=lambda line: print(line, flush=True))
    with writing_folder(out) as folder:  # the export appears whole or not at all
        export(policy, folder, half=args.half)
    print(f"refitted in {report['seconds'] / 60:.1f} min; wrote {out} ({CARD})")
    return 0


def _veto_threshold(value: float) -> float:
    if not 0.0 <= value < 1.0:
        raise ConfigError(f"--veto-threshold: {value:g} is not allowed; allowed: a number in [0, 1)")
    return value


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Greedy play of a restored policy on held-out scenarios, against the clairvoyant planner."""
    import json
    import os
    import time

    from formation.evaluate import evaluate_policy, format_report
    from formation.policy import how_trained, load, training_line

    for name in ("episodes", "workers"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise ConfigError(f"--{name}: {value} is not allowed; allowed: an integer >= 1")
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed: {args.seed} is not allowed; allowed: an integer >= 0")
    if args.shield < 0:
        raise ConfigError(f"--shield: {args.shield} is not allowed; allowed: an integer >= 0 (steps ahead; 0: none)")
    if args.json:
        _check_report_path(args.json)
    policy = load(local_run_folder(args.checkpoint)).shielded(args.shield)
    if args.veto_threshold is not None:
        policy = policy.with_veto_threshold(_veto_threshold(args.veto_threshold))
    if args.veto_fallback is not None:
        policy = policy.with_veto_fallback(args.veto_fallback)
    trained_on = policy.game
    changes = parse_overrides(args.set)
    policy = _playing(policy, args.setting, args.followers, changes)
    episodes = args.episodes or policy.eval_settings["episodes"]
    seed = policy.eval_settings["seed"] if args.seed is None else args.seed
    workers = args.workers or min(os.cpu_count() or 1, 8)
    tty = sys.stderr.isatty()
    last = [0.0]

    def progress(phase: str, done: int, total: int) -> None:
        now = time.monotonic()
        if done < total and not tty and now - last[0] < 10.0:
            return
        last[0] = now
        end = "\n" if (done == total or not tty) else ""
        start = "\r" if tty else ""
        print(f"{start}{phase}: {done}/{total} episodes", end=end, file=sys.stderr, flush=True)

    report = evaluate_policy(policy.game, policy.act_batch, episodes, seed, workers=workers, progress=progress)
    report = {"checkpoint": str(args.checkpoint), "setting": policy.game.setting, "followers": policy.game.n_followers,
              "game_changes": changes, "env_steps": policy.env_steps,
              "shield": args.shield, "veto_threshold": policy.veto_threshold if policy.learned_veto else None,
              "veto_fallback": policy.veto_fallback if policy.learned_veto else None,
              "trained": how_trained(policy), **report}
    print(f"{args.checkpoint}: {episodes} greedy episodes"
          + (f" after {policy.env_steps:,} env steps" if policy.env_steps is not None else "")
          + (f", behind a shield of {args.shield} steps" if args.shield else "")
          + (f", veto above {policy.veto_threshold:g} (else {policy.veto_fallback.replace('_', ' ')})"
             if policy.learned_veto else ""))
    if (trained := training_line(policy.training)) is not None:  # cards from before it have none: nothing
        print(trained)
    games = ((policy.training or {}).get("config") or {}).get("games")
    trained_games = {(s, k) for s in games["settings"] for k in games["followers"]} if games else \
        {(trained_on.setting, trained_on.n_followers)}
    if (policy.game.setting, policy.game.n_followers) not in trained_games or changes:
        what = f"settings {games['settings']} with {games['followers']} followers" if games else \
            f"setting {trained_on.setting} with {trained_on.n_followers}"
        changed = "".join(f", {key}={value}" for key, value in changes.items())
        print(f"zero-shot: playing setting {policy.game.setting} with {policy.game.n_followers} follower(s){changed}; "
              f"trained on {what}")
    print(format_report(report))
    if args.json:
        write_text_whole(args.json, json.dumps(report, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


def _check_report_path(given: str) -> None:
    """``--json``: a new file, or an earlier evaluation report to replace (as docs/RESULTS.md's commands
    do); never a folder or any other file."""
    import json

    path = check_writable(given, "--json")
    if not path.exists():
        return
    if path.is_dir():
        raise ConfigError(f"--json: {given!r} is a folder; allowed: a file path, e.g. {given.rstrip('/')}/eval.json")
    try:
        earlier = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        earlier = None
    if not (isinstance(earlier, dict) and {"checkpoint", "episodes", "success"} <= earlier.keys()):
        raise ConfigError(f"--json: {given!r} exists and is not an evaluation report; allowed: a new file or an "
                          f"earlier report (nothing else is overwritten)")


def _playing(policy, setting: int | None, followers: int | None, changes: dict[str, Any] | None = None):
    """``policy`` playing ``--setting`` and ``--followers`` (``Policy.for_game``; None: its own) with the game's
    fields ``--set`` changes, or a one-line error naming the flag."""
    changes = changes or {}
    for key, flag in (("setting", "--setting"), ("n_followers", "--followers")):
        if key in changes:
            raise ConfigError(f"--set {key}: is not allowed; allowed: {flag}")
    if setting is None and followers is None and not changes:
        return policy
    try:
        game = policy.game.variant(setting, followers)
    except ConfigError as err:
        about_team = str(err).startswith(("n_followers", "follower_starts"))
        raise ConfigError(f"{'--followers' if about_team or setting is None else '--setting'}: {err}") from None
    try:
        game = game.replace(**changes)
    except ConfigError as err:
        raise ConfigError(f"--set {err}") from None
    try:
        return policy.for_game(game)
    except ConfigError as err:
        about_team = str(err).startswith("game.n_followers")
        flag = "--followers" if about_team else "--setting" if setting is not None else "--set"
        raise ConfigError(f"{flag}: {err}") from None


def cmd_render(args: argparse.Namespace) -> int:
    """The paper's pictures of a trained policy: episodes.gif, paths.png, q_values.png, training.png."""
    from formation.pictures import render
    from formation.policy import load

    if args.episodes < 1:
        raise ConfigError(f"--episodes: {args.episodes} is not allowed; allowed: an integer >= 1")
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed: {args.seed} is not allowed; allowed: an integer >= 0")
    if not is_uri(args.checkpoint):
        check_outside(args.out, _source(args.checkpoint), "--out")
    out = _picture_folder(args.out)
    path = local_run_folder(args.checkpoint)
    check_outside(out, _source(path), "--out", given=args.checkpoint)
    policy = _playing(load(path), args.setting, args.followers, parse_overrides(args.set))
    run_dir = path if (path / "config.yaml").is_file() else path.parent
    seed = policy.eval_settings["seed"] if args.seed is None else args.seed
    with writing_into(out) as folder:  # pictures of the same names, drawn before, are replaced whole
        written = render(policy, folder, episodes=args.episodes, seed=seed, metrics=run_dir / "metrics.jsonl")
    for picture in written:
        print(f"wrote {out / picture.name}")
    return 0


def version() -> str:
    """The installed package's version; in a source tree that is not installed, ``formation.__version__``."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("formation")
    except PackageNotFoundError:
        import formation

        return formation.__version__


class _Parser(argparse.ArgumentParser):
    """argparse's own messages, in one line (usage behind --help) like every other error here."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="formation", description=__doc__)
    parser.add_argument("--version", action="version", version=f"formation {version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    show = sub.add_parser("show", help="plan the best path with the clairvoyant planner and write a GIF")
    show.add_argument("--setting", type=int, default=1, help="named setting 1-4 (default 1)")
    show.add_argument("--seed", type=int, default=0, help="first scenario seed (default 0)")
    show.add_argument("--episodes", type=int, default=3, help="episodes side by side (default 3)")
    show.add_argument("--out", default="runs/show", help="output folder (default runs/show)")
    show.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                      help="override a game config field, e.g. --set n_followers=2")
    show.set_defaults(run=cmd_show)

    train = sub.add_parser("train", help="train the leader and follower policies from a config")
    train.add_argument("config", nargs="?", help="a YAML config, e.g. configs/quickstart.yaml")
    train.add_argument("--out", help="run folder, or a storage URI such as s3://bucket/runs/s1 "
                                      "(default runs/<config name>)")
    train.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    train.add_argument("--no-ray", action="store_true",
                       help="train in this one process, without Ray (formation.recipe.loop)")
    train.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                       help="override a config value, e.g. --set train.gamma=0.99")
    train.set_defaults(run=cmd_train)

    evaluate = sub.add_parser("evaluate", help="greedy play of a trained policy against the clairvoyant planner")
    evaluate.add_argument("checkpoint", help=CHECKPOINT_HELP)
    evaluate.add_argument("--episodes", type=int, help="episodes (default: the run's eval.episodes, or 200)")
    evaluate.add_argument("--seed", type=int, help="scenario seed (default: the run's eval.seed, or 1000000)")
    evaluate.add_argument("--setting", type=int,
                          help="play named setting K (default: the policy's own game)")
    evaluate.add_argument("--followers", type=int, metavar="N",
                          help="play a team of N followers (default: the policy's own)")
    evaluate.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                          help="play the game with a field changed (docs/CONFIG.md, section game), e.g. --set "
                               "n_obstacles=6 or --set obstacle_speeds=[3]")
    evaluate.add_argument("--workers", type=int, help="processes for the planner (default: the CPU cores, up to 8)")
    evaluate.add_argument("--json", metavar="PATH", help="also write the numbers as JSON")
    evaluate.add_argument("--shield", type=int, default=0, metavar="STEPS",
                          help="play behind a safety shield that vetoes moves lost within STEPS steps "
                               "(formation.shield; default 0: the networks alone)")
    evaluate.add_argument("--veto-threshold", type=float, metavar="P",
                          help="keep to the joint moves the safety heads judge safe with a probability above P "
                               "(default: the policy's own, 0.5 or what formation refit set)")
    evaluate.add_argument("--veto-fallback", choices=VETO_FALLBACKS,
                          help="where no joint move is above the threshold, keep to those above one half (and where "
                               "none is, to all) or to the most probably safe (default: the policy's own)")
    evaluate.set_defaults(run=cmd_evaluate)

    export = sub.add_parser("export", help="write a checkpoint's networks and a policy card for torch alone")
    export.add_argument("checkpoint", help=CHECKPOINT_HELP)
    export.add_argument("dir", help="output folder: <module>.pt and policy.json")
    export.add_argument("--half", action="store_true",
                        help="store the weights as float16: half the size; evaluate the export itself")
    export.add_argument("--veto-threshold", type=float, metavar="P",
                        help="the exported team's veto keeps to the joint moves its safety heads judge safe with a "
                             "probability above P (default: the policy's own)")
    export.add_argument("--veto-fallback", choices=VETO_FALLBACKS,
                        help="where no joint move is above the threshold, the exported team's veto keeps to those "
                             "above one half (and where none is, to all) or to the most probably safe (default: "
                             "the policy's own)")
    export.set_defaults(run=cmd_export)

    refit = sub.add_parser("refit", help="refit a trained team's safety heads on fresh states of its own play, "
                                         "labelled by the planner; write the team as an export")
    refit.add_argument("checkpoint", help=CHECKPOINT_HELP + ", whose networks have safety heads")
    refit.add_argument("dir", help="a new output folder: <module>.pt and policy.json, as formation export writes")
    refit.add_argument("--set", action="append", default=[], metavar="refit.KEY=VALUE",
                       help="override a refit setting (default: the run's refit section), e.g. --set refit.rounds=3")
    refit.add_argument("--half", action="store_true", help="store the weights as float16, as formation export --half")
    refit.set_defaults(run=cmd_refit)

    render = sub.add_parser("render", help="draw a trained policy's episodes, paths, Q-values and training curves")
    render.add_argument("checkpoint", help=CHECKPOINT_HELP)
    render.add_argument("--out", required=True, help="output folder for the pictures")
    render.add_argument("--episodes", type=int, default=4, help="greedy episodes to show (default 4)")
    render.add_argument("--seed", type=int, help="scenario seed (default: the run's eval.seed, or 1000000)")
    render.add_argument("--setting", type=int, help="play named setting K (default: the policy's own game)")
    render.add_argument("--followers", type=int, metavar="N", help="play a team of N followers (default: the "
                        "policy's own)")
    render.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="play the game with a field changed, as formation evaluate --set")
    render.set_defaults(run=cmd_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except ConfigError as err:
        print(f"formation: error: {err}", file=sys.stderr)
        return 2
    except RunFailed as err:
        print(f"formation: run failed: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("formation: interrupted", file=sys.stderr)
        return 130
    except OSError as err:  # a disk that fills or a folder that goes away mid-way: nothing half-written stays
        where = f"{str(err.filename)!r}: " if err.filename else ""
        print(f"formation: error: {where}{err.strerror or err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
