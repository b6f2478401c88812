"""Env steps and wall time a run folder trained for, across its `--resume` sessions.

    .venv/bin/python experiments/training_time.py runs/s1_pix_win [runs/s2_pix ...]

Each session's rows in metrics.jsonl count seconds from that session's start; a session ends
where the count falls back. Prints one line per run: env steps, sessions, hours, and greedy
success at each evaluation."""

from __future__ import annotations

import json
from pathlib import Path

from _common import parser


def sessions(rows: list[dict]) -> list[float]:
    """Seconds trained in each session."""
    spans, last = [], None
    for row in rows:
        seconds = row["seconds"]
        if last is not None and seconds < last:
            spans.append(last)
        last = seconds
    if last is not None:
        spans.append(last)
    return spans


def main() -> None:
    p = parser(__doc__)
    p.add_argument("runs", nargs="+", help="run folders of `formation train`")
    args = p.parse_args()
    for run in args.runs:
        rows = [json.loads(line) for line in (Path(run) / "metrics.jsonl").read_text().splitlines() if line.strip()]
        spans = sessions(rows)
        evals, last = [], None
        for row in rows:
            value = row.get("greedy/success")
            if value is not None and value != last:
                evals.append(f"{int(row['env_steps']):,}: {value:.1%}")
                last = value
        print(f"{run}: {int(rows[-1]['env_steps']):,} env steps in {len(spans)} session(s), "
              f"{sum(spans) / 3600:.2f} h of training; greedy success " + ", ".join(evals))


if __name__ == "__main__":
    main()
