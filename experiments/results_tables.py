"""docs/RESULTS.md's tables, from the `formation evaluate --json` reports in docs/results/.

    .venv/bin/python experiments/results_tables.py

Each report is `formation evaluate <policy> --episodes 1000 --seed 2000000 --json docs/results/<name>.json`;
each report's training hours are in docs/results/training_hours.json, as experiments/training_time.py
measured them from the run folder's metrics.jsonl (with the machine, where it was not this one), and the
hours of `formation refit` after it, as its export's card records them (``refit.seconds``)."""

from __future__ import annotations

import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parent.parent / "docs" / "results"
# Table 3 of the paper: mean returns (leader, follower) after 10-40 h on a GTX 1080 Ti, and the best possible
PAPER = {1: (51.0, 21.4, 75, 25), 2: (54.6, 22.5, 75, 25), 3: (71.5, 42.9, 100, 50), 4: (68.8, 45.7, 100, 50)}


def pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def row(name: str, r: dict, hours: float | dict | None) -> str:
    low, high = r["success_ci95"]
    p = r["planner"]
    setting = r["setting"]
    paper = PAPER.get(setting)
    ours = r["return_mean"]
    follower = ours.get("follower", ours.get("follower_1"))
    ratio = p["return_ratio"]
    # a number: hours on this 2-core machine; {"hours": h, "where": machine}: hours on another; "refit_hours":
    # the hours `formation refit` took after training
    where = f" ({hours['where']})" if isinstance(hours, dict) and "where" in hours else ""
    refit = f" + {hours['refit_hours']:.2f} h refit" if isinstance(hours, dict) and "refit_hours" in hours else ""
    hours = hours["hours"] if isinstance(hours, dict) else hours
    time = f"{hours:.2f} h{where}{refit}" if hours is not None else "n/a"
    cells = [name, f"{r['env_steps']:,}", time,
             f"**{pct(r['success'])}** ({pct(low)}-{pct(high)})",
             pct(r["leader_collision"]), pct(r["follower_collision"]), pct(r["formation_broken"]), pct(r["timeout"]),
             f"{r['steps_success_mean']:.2f} / {p['planner_steps_on_successes_mean']:.2f}"
             if r["steps_success_mean"] is not None else f"none / {p['planner_steps_mean']:.2f}",
             f"{ours['leader']:.1f} / {follower:.1f}",
             f"{paper[0]:.1f} / {paper[1]:.1f} ({paper[0] / paper[2]:.3f} / {paper[1] / paper[3]:.3f})"
             if paper else "n/a",
             f"{ratio['leader']:.3f} / {ratio['follower']:.3f}"]
    return "| " + " | ".join(cells) + " |"


HEADER = ("| policy | env steps | training | success (95% CI) | leader collision | follower collision | "
          "formation break | time-out | steps: ours / planner | mean return leader / follower | "
          "paper Table 3 (over its best) | ours over the planner's return, leader / follower |\n" + "| --- " * 12 + "|")


def main() -> None:
    hours = json.loads((RESULTS / "training_hours.json").read_text())
    print(HEADER)
    for path in sorted(RESULTS.glob("setting*.json")):
        report = json.loads(path.read_text())
        print(row(path.stem, report, hours.get(path.stem)))


if __name__ == "__main__":
    main()
