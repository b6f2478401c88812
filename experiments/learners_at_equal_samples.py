"""One learner against two data-parallel learners at equal samples: configs/small.yaml with 2 rollout actors and
2 replay shards, trained by `formation train` with resources.num_learners 1 and 2 at each seed.

    .venv/bin/python experiments/learners_at_equal_samples.py --out /tmp/learners [--seeds 0,1,2] [--json FILE]

Both take the same env steps and the same updates of train.batch_size records each: two learners pull half the
batch each and average their gradients. Prints each run's greedy success at the end (its 200 evaluation games),
the mean and spread of each, and writes them to --json (docs/results/learners.json holds the last run's)."""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
from pathlib import Path

from _common import ROOT, parser

CONFIG = "configs/small.yaml"
SHARED = {"resources.num_rollout_actors": 2, "resources.num_replay_shards": 2, "resources.cpus_per_rollout_actor": 0.5}


def train(out: Path, learners: int, seed: int) -> dict:
    """One run's result.json (trained unless the folder holds a finished one)."""
    if not (out / "result.json").is_file():
        sets = {**SHARED, "resources.num_learners": learners, "train.seed": seed}
        # `formation train` in a process of its own, on a Ray of 4 logical CPUs (2 learners and 2 actors' halves
        # fit on a 2-core machine too)
        code = ("import ray; from formation.train import train; "
                "ray.init(num_cpus=4, include_dashboard=False, log_to_driver=False); "
                f"train({CONFIG!r}, {str(out)!r}, overrides={sets!r}, quiet=True)")
        subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return json.loads((out / "result.json").read_text())


def main() -> None:
    p = parser(__doc__)
    p.add_argument("--out", type=Path, required=True, help="folder for the run folders (kept: a rerun reuses them)")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    runs = []
    for seed in seeds:
        for learners in (1, 2):
            out = args.out / f"learners{learners}_seed{seed}"
            result = train(out, learners, seed)
            last = json.loads((out / "metrics.jsonl").read_text().splitlines()[-1])
            runs.append({"learners": learners, "seed": seed, "success": result["greedy"]["success"],
                         "env_steps": result["env_steps"], "learner_updates": last["learner_updates"]})
            print(f"learners {learners}  seed {seed}  greedy success {runs[-1]['success']:.1%}  "
                  f"env steps {result['env_steps']:,}  updates {last['learner_updates']:,}", flush=True)
    for learners in (1, 2):
        rates = [r["success"] for r in runs if r["learners"] == learners]
        print(f"{learners} learner(s): mean {statistics.mean(rates):.1%}, from {min(rates):.1%} to {max(rates):.1%}")
    if args.json:
        args.json.write_text(json.dumps({"config": CONFIG, "overrides": SHARED, "runs": runs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
