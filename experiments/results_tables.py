"""docs/RESULTS.md's tables of the test scenarios and of the returns against the paper's Table 3, from the
`formation evaluate --json` reports in docs/results/.

    .venv/bin/python experiments/results_tables.py

Each report is `formation evaluate <policy> --episodes 1000 --seed 2000000 --json docs/results/<name>.json`:
`settingK_seedS.json` of the run folder of `formation train configs/settingK.yaml --set train.seed=S`,
`settingK.json` of the shipped `policies/settingK`, and the grid and paper's-recipe rows. A report records how
its team was trained (``trained``: env steps, wall seconds of training and refit, hardware); for the rows
older than that, docs/results/training_hours.json has the hours.

Learning from the reward alone (docs/results/reward_only/): `settingK.json` is the test report of the shipped
`policies/reward_only/settingK`; `ingredients/*.json` are validation reports (`--seed 3000000`) of the runs
that measured what each ingredient of the reward-only recipe gained (INGREDIENTS names them);
`reproduced/settingK_seedS.json` validation reports of the config run again with `--set train.seed=S` (its last
team; `_noray`: trained with `--no-ray`; `_best`: the run's `best/`). Every reward-only report must record a
training without the planner.

The generalist team (docs/results/generalist/): `settingK_followersN.json`, `formation evaluate policies/generalist
--setting K --followers N --episodes 1000 --seed 2000000`, on the test scenarios of its own games;
`validation/settingK_followersN.json`, the same on 200 validation scenarios (`--episodes 200 --seed 3000000`);
`unseen/settingK_followersN_TAG.json`, the validation run with `--set` changing the game as TAG names (UNSEEN).

Prints the tables as Markdown; `--readme`, README.md's settings table; `--recipe`, docs/RECIPE.md's table of
what each ingredient of the reward-only recipe gained.
"""

from __future__ import annotations

import json

from _common import RESULTS, parser

# Table 3 of the paper: mean returns (leader, follower) after 10-40 h on a GTX 1080 Ti, and the best possible
PAPER = {1: (51.0, 21.4, 75, 25), 2: (54.6, 22.5, 75, 25), 3: (71.5, 42.9, 100, 50), 4: (68.8, 45.7, 100, 50)}


def pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def success_cell(r: dict, bold: bool = False) -> str:
    """A report's success rate with its 95% interval; ``bold``: the rate in bold (a shipped team's)."""
    low, high = r["success_ci95"]
    rate = f"**{pct(r['success'])}**" if bold else pct(r["success"])
    return f"{rate} ({pct(low)[:-1]}-{pct(high)})"


def label(stem: str) -> str:
    """A report's row name: `policies/settingK` for a shipped policy, else what it was trained as."""
    setting, _, kind = stem.partition("_")
    k = setting.removeprefix("setting")
    return {"": f"`policies/{stem}`", "grid": f"setting {k}, grid (not shipped)",
            "paper_recipe": f"setting {k}, the paper's recipe"}[kind]


def one_command_row(stem: str, r: dict, shipped: dict | None) -> str:
    """A row of the one-command table: a run of `formation train configs/settingK.yaml` and its seed."""
    trained = r["trained"]
    minutes = trained["wall_seconds"] / 60
    refit = (trained["refit_seconds"] or 0.0) / 60
    steps = "none" if r["steps_success_mean"] is None else \
        f"{r['steps_success_mean']:.2f} / {r['planner']['planner_steps_on_successes_mean']:.2f}"
    ships = shipped is not None and shipped.get("trained") is not None and \
        shipped["trained"]["env_steps"] == trained["env_steps"] and shipped["trained"]["seed"] == trained["seed"]
    cells = [str(r["setting"]), str(trained["seed"]), success_cell(r),
             pct(r["leader_collision"]), pct(r["follower_collision"]), pct(r["formation_broken"]), pct(r["timeout"]),
             steps, f"{trained['env_steps']:,}", f"{minutes + refit:.1f} ({minutes:.1f} + {refit:.1f})",
             "yes" if ships else ""]
    return "| " + " | ".join(cells) + " |"


def training(hours: float | dict | None) -> str:
    """A number: hours of `formation train`; {"hours": h, "refit_hours": r}: then r hours of `formation refit`."""
    if hours is None:
        return "n/a"
    if isinstance(hours, dict):
        refit = f" + {hours['refit_hours']:.2f} h refit" if "refit_hours" in hours else ""
        return f"{hours['hours']:.2f} h{refit}"
    return f"{hours:.2f} h"


def test_row(stem: str, r: dict, hours: float | dict | None) -> str:
    p = r["planner"]
    success = success_cell(r, bold="_" not in stem)  # shipped policies in bold
    if r["steps_success_mean"] is None:
        steps = f"none / {p['planner_steps_mean']:.2f}"
    else:
        steps = f"{r['steps_success_mean']:.2f} / {p['planner_steps_on_successes_mean']:.2f}"
    trained = r.get("trained")
    if trained and trained.get("wall_seconds"):  # the report's own record, where it has one
        hours = {"hours": trained["wall_seconds"] / 3600,
                 **({"refit_hours": trained["refit_seconds"] / 3600} if trained["refit_seconds"] else {})}
    cells = [label(stem), f"{r['env_steps']:,}", training(hours), success,
             pct(r["leader_collision"]), pct(r["follower_collision"]), pct(r["formation_broken"]), pct(r["timeout"]),
             steps]
    return "| " + " | ".join(cells) + " |"


def returns_row(stem: str, r: dict) -> str:
    ours = r["return_mean"]
    follower = ours.get("follower", ours.get("follower_1"))
    ratio = r["planner"]["return_ratio"]
    paper = PAPER[r["setting"]] if "_" not in stem else None
    name = stem.removeprefix("setting") if paper else label(stem).removeprefix("setting ")
    cells = [name, f"{ours['leader']:.1f} / {follower:.1f}", f"{ratio['leader']:.3f} / {ratio['follower']:.3f}",
             f"{paper[0]:.1f} / {paper[1]:.1f}" if paper else "",
             f"{paper[0] / paper[2]:.3f} / {paper[1] / paper[3]:.3f}" if paper else ""]
    return "| " + " | ".join(cells) + " |"


def order(stem: str) -> tuple[int, str]:
    """Shipped policies first, then the grid runs, then the paper's recipe."""
    return ({"": 0, "grid": 1, "paper_recipe": 2}[stem.partition("_")[2]], stem)


# the reward-only ingredient runs, in the table's order: what each trained with (docs/RESULTS.md has the commands)
INGREDIENTS = {
    "grid_paper_reward_seed0": "setting 1, grid: the paper's training reward (+1 a step in formation)",
    "grid_kept0_seed0": "setting 1, grid: kept 0",
    "grid_kept0_seed1": "setting 1, grid: kept 0",
    "grid_kept0_team_seed0": "setting 1, grid: kept 0, team reward",
    "grid_kept0_team_seed1": "setting 1, grid: kept 0, team reward",
    "grid_kept0_team_noshaping_seed0": "setting 1, grid: kept 0, team reward, no shaping",
    "pixels_setting1_nocompass_seed0": "setting 1, pixels: kept 0, team reward (`configs/reward_only/setting1.yaml` "
                                       "before the averaged team)",
    "pixels_setting1_seed0": "setting 1, pixels: kept 0, team reward, the destination compass",
    "pixels_setting2_nocompass_seed0": "setting 2, pixels: kept 0, team reward (`configs/reward_only/setting2.yaml` "
                                       "before the averaged team)",
    "pixels_setting2_seed0": "setting 2, pixels: kept 0, team reward, the destination compass",
    "pixels_setting3_nocompass_seed0": "setting 3, pixels: kept 0, team reward (`configs/reward_only/setting3.yaml` "
                                       "before the averaged team)",
    "pixels_setting3_seed0": "setting 3, pixels: kept 0, team reward, the destination compass",
    "pixels_setting4_nocompass_seed0": "setting 4, pixels: kept 0, team reward (`configs/reward_only/setting4.yaml` "
                                       "before the averaged team)",
    "pixels_setting4_seed0": "setting 4, pixels: kept 0, team reward, the destination compass",
}


def reward_only(report: dict, name: str) -> dict:
    """The report's training record, once checked to be from the reward alone."""
    trained = report.get("trained") or {}
    if trained.get("planner_options") != []:
        raise SystemExit(f"{name}: its team was not trained from the reward alone "
                         f"(planner options {trained.get('planner_options')!r})")
    return trained


def steps_cell(r: dict) -> str:
    """Steps of successes against the planner's on the same scenarios, and how much longer in percent; against a
    lower bound on the planner's (a team of 3-4 followers), "at least" that."""
    if r["steps_success_mean"] is None:
        return "none"
    ours, planner = r["steps_success_mean"], r["planner"]["planner_steps_on_successes_mean"]
    if not r["planner"].get("planner_exact", True):
        return f"{ours:.2f} / at least {planner:.2f}"
    return f"{ours:.2f} / {planner:.2f} (+{100 * (ours / planner - 1):.1f}%)"


def reward_only_tables() -> None:
    folder = RESULTS / "reward_only"
    print("| policy | env steps | training | success (95% CI) | leader collision | follower collision | "
          "formation break | time-out | steps: ours / planner |\n" + "| --- " * 9 + "|")
    for path in sorted(folder.glob("setting*.json")):
        r = json.loads(path.read_text())
        trained = reward_only(r, str(path))
        cells = [f"`policies/reward_only/{path.stem}`", f"{r['env_steps']:,}",
                 f"{trained['wall_seconds'] / 3600:.2f} h", success_cell(r, bold=True),
                 pct(r["leader_collision"]), pct(r["follower_collision"]), pct(r["formation_broken"]),
                 pct(r["timeout"]), steps_cell(r)]
        print("| " + " | ".join(cells) + " |")


def ingredients_table() -> None:
    """docs/RECIPE.md's table: what each ingredient of the reward-only recipe gained, on validation."""
    folder = RESULTS / "reward_only"
    print("| training | seed | env steps | validation success (95% CI) | time-out | steps: ours / planner |\n"
          + "| --- " * 6 + "|")
    for stem, what in INGREDIENTS.items():
        path = folder / "ingredients" / f"{stem}.json"
        if not path.exists():
            continue
        r = json.loads(path.read_text())
        trained = reward_only(r, str(path))
        cells = [what, str(trained["seed"]), f"{r['env_steps']:,}", success_cell(r), pct(r["timeout"]),
                 steps_cell(r)]
        print("| " + " | ".join(cells) + " |")


# the README's settings table: each setting's board, as docs/GAME.md gives them
BOARDS = {1: "25x25, 3 obstacles, side by side", 2: "25x25, 3 obstacles, one behind the other",
          3: "50x50, 8 obstacles, side by side", 4: "50x50, 8 obstacles, one behind the other"}


def reproduced_table() -> None:
    """Each reward-only config run again from the config alone, on the validation scenarios: per run, its last team
    (`reward_only/reproduced/settingK_seedS[_noray].json`) and, where the run kept one, the team of its best
    training evaluation (`settingK_seedS_noray_best.json`), beside the shipped team (`SHIPPED_VALIDATION`)."""
    folder = RESULTS / "reward_only" / "reproduced"
    if not any(folder.glob("*.json")):
        return
    print("\n| config | seed | trained | last team: validation (95% CI), steps | "
          "`best/`: env steps, validation, steps | shipped team |\n" + "| --- " * 6 + "|")
    for path in sorted(folder.glob("setting*_seed*.json")):
        if path.stem.endswith("_best"):
            continue
        r = json.loads(path.read_text())
        trained = reward_only(r, str(path))
        setting = path.stem.partition("_")[0]
        best_path = path.with_name(f"{path.stem}_best.json")
        best = "not kept"
        if best_path.exists():
            b = json.loads(best_path.read_text())
            reward_only(b, str(best_path))
            best = f"{b['env_steps']:,}, {success_cell(b)}, {steps_cell(b)}"
        shipped = json.loads((RESULTS / "reward_only" / SHIPPED_VALIDATION[setting]).read_text())
        how = "`--no-ray`" if path.stem.endswith("_noray") else "Ray"
        cells = [f"`configs/reward_only/{setting}.yaml`", str(trained["seed"]),
                 f"{how}, {r['env_steps']:,} env steps, {trained['wall_seconds'] / 60:.1f} min",
                 f"{success_cell(r)}, {steps_cell(r)}", best, pct(shipped["success"])]
        print("| " + " | ".join(cells) + " |")


# the validation report of each shipped reward-only team (docs/results/reward_only/...)
SHIPPED_VALIDATION = {"setting1": "reproduced/setting1_seed1_noray.json",
                      "setting2": "reproduced/setting2_seed0_noray_best.json",
                      "setting3": "reproduced/setting3_seed1_noray.json",
                      "setting4": "reproduced/setting4_seed1_noray.json"}


def teams_table() -> None:
    """The generalist team on each of its games, on the test scenarios (`generalist/settingK_followersN.json`)
    beside its validation success (`generalist/validation/`): setting x team size."""
    folder = RESULTS / "generalist"
    if not any(folder.glob("*.json")):
        return
    print("\n| setting | followers | success (95% CI) | leader collision | follower collision | formation break | "
          "time-out | steps: ours / planner | validation |\n" + "| --- " * 9 + "|")
    for path in sorted(folder.glob("setting*_followers*.json")):
        r = json.loads(path.read_text())
        reward_only(r, str(path))
        validation = same_team(r, json.loads((folder / "validation" / path.name).read_text()),
                               f"generalist/validation/{path.name}")
        cells = [str(r["setting"]), str(r["followers"]), success_cell(r), pct(r["leader_collision"]),
                 pct(r["follower_collision"]), pct(r["formation_broken"]), pct(r["timeout"]), steps_cell(r),
                 pct(validation["success"])]
        print("| " + " | ".join(cells) + " |")


def same_team(report: dict, other: dict, name: str) -> dict:
    """``other`` (the report ``name``), once checked to be of the team of ``report`` (the same training: its env
    steps and wall seconds)."""
    key = [(r["env_steps"], (r.get("trained") or {}).get("wall_seconds")) for r in (report, other)]
    if key[0] != key[1]:
        raise SystemExit(f"{name}: not the team of the reports beside it (env steps, training seconds: {key[1]} "
                         f"against {key[0]})")
    return other


# `generalist/unseen/settingK_followersN_TAG.json`: `formation evaluate policies/generalist --setting K --followers N
# --set ...`, a game its training never drew; TAG names the change against the setting's own game
UNSEEN = {"obstacles+2": "2 obstacles more", "obstacles+4": "4 obstacles more", "speeds1-3": "speeds 1-3"}


def unseen_table() -> None:
    """The generalist team, zero-shot, on games with more or faster obstacles than its training drew, beside its
    own games (`generalist/validation/`), all on the validation scenarios: success with its 95% interval."""
    folder = RESULTS / "generalist" / "unseen"
    if not any(folder.glob("*.json")):
        return
    rows: dict[tuple[int, int], dict[str, dict]] = {}
    for path in sorted(folder.glob("setting*_followers*_*.json")):
        r = json.loads(path.read_text())
        tag = path.stem.split("_")[-1]
        if tag not in UNSEEN or not r.get("game_changes"):
            raise SystemExit(f"{path}: not a report of a changed game named by one of {list(UNSEEN)}")
        reward_only(r, str(path))
        rows.setdefault((r["setting"], r["followers"]), {})[tag] = r
    print("\n| setting | followers | as trained | " + " | ".join(UNSEEN.values()) + " |\n"
          + "| --- " * (3 + len(UNSEEN)) + "|")
    for (setting, followers), changed in sorted(rows.items()):
        own = json.loads((RESULTS / "generalist" / "validation" / f"setting{setting}_followers{followers}.json")
                         .read_text())
        for tag, r in changed.items():
            same_team(own, r, f"generalist/unseen/setting{setting}_followers{followers}_{tag}.json")
        cells = [str(setting), str(followers), success_cell(own)]
        cells += [success_cell(changed[tag]) if tag in changed else "not played" for tag in UNSEEN]
        print("| " + " | ".join(cells) + " |")


def readme_table() -> None:
    """README.md's four rows: each setting's shipped teams on the test scenarios, from the reward alone (the
    default recipe) and with the teacher."""
    print("| setting | board, formation | default recipe: success, steps over the planner's | "
          "teacher recipe: success, steps over the planner's |\n" + "| --- " * 4 + "|")
    for k, board in BOARDS.items():
        cells = [str(k), board]
        for path in (RESULTS / "reward_only" / f"setting{k}.json", RESULTS / f"setting{k}.json"):
            r = json.loads(path.read_text())
            ours, planner = r["steps_success_mean"], r["planner"]["planner_steps_on_successes_mean"]
            cells.append(f"**{pct(r['success'])}**, +{100 * (ours / planner - 1):.1f}%")
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    args = parser(__doc__)
    args.add_argument("--readme", action="store_true", help="print README.md's settings table alone")
    args.add_argument("--recipe", action="store_true", help="print docs/RECIPE.md's table of the ingredients alone")
    given = args.parse_args()
    if given.readme:
        readme_table()
        return
    if given.recipe:
        ingredients_table()
        return
    hours = json.loads((RESULTS / "training_hours.json").read_text())
    reports = {path.stem: json.loads(path.read_text()) for path in RESULTS.glob("setting*.json")}
    runs = sorted(stem for stem in reports if "_seed" in stem)
    if runs:
        print("| setting | seed | success (95% CI) | leader collision | follower collision | formation break | "
              "time-out | steps: ours / planner | env steps | minutes: training + refit | shipped |\n"
              + "| --- " * 11 + "|")
        for stem in runs:
            print(one_command_row(stem, reports[stem], reports.get(stem.partition("_")[0])))
        print()
    stems = sorted((stem for stem in reports if stem not in runs), key=order)
    print("| policy | env steps | training | success (95% CI) | leader collision | follower collision | "
          "formation break | time-out | steps: ours / planner |\n" + "| --- " * 9 + "|")
    for stem in stems:
        print(test_row(stem, reports[stem], hours.get(stem)))
    print("\n| setting | ours: mean return, leader / follower | ours over the planner's | paper: mean return | "
          "paper over its best |\n" + "| --- " * 5 + "|")
    for stem in stems:
        if not stem.endswith("_grid"):
            print(returns_row(stem, reports[stem]))
    print()
    reward_only_tables()
    reproduced_table()
    teams_table()
    unseen_table()


if __name__ == "__main__":
    main()
