"""The shared preamble of the scripts in experiments/: how they run, and the seeds and paths the docs use.

Each script reproduces numbers that docs/RESULTS.md cites. Run it from the repository root with the
project's environment (``make test`` or ``make run`` builds ``.venv/``):

    .venv/bin/python experiments/<script>.py --help

Each prints plain text (or a Markdown table) to stdout and writes nothing else. Scripts that play a policy
take a run folder, its checkpoint/ or an export (``formation.policy.load``), ``--episodes`` and ``--seed``
(by default the docs' 1000 test scenarios, seed 2,000,000; the validation scenarios are seed 3,000,000),
and use one torch thread, so their numbers do not depend on the machine's cores.
"""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"  # the `formation evaluate --json` reports docs/RESULTS.md's tables come from
TEST_SEED = 2_000_000  # docs/RESULTS.md's test scenarios: seeds 2,000,000-2,000,999, never drawn in training
VALIDATION_SEED = 3_000_000  # the scenarios every shipping choice was made on
EPISODES = 1000


def parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser whose help is the script's docstring."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def policy_parser(doc: str | None) -> argparse.ArgumentParser:
    """``parser`` with the arguments of a script that plays a policy: POLICY, --episodes, --seed."""
    p = parser(doc)
    p.add_argument("policy", type=Path, help="a run folder, its checkpoint/ folder, or a `formation export` folder")
    p.add_argument("--episodes", type=int, default=EPISODES, help=f"episodes (default {EPISODES})")
    p.add_argument("--seed", type=int, default=TEST_SEED,
                   help=f"scenario seed (default {TEST_SEED:,}, the test scenarios; {VALIDATION_SEED:,}: validation)")
    return p


def one_thread() -> None:
    """One torch thread: the same numbers and about the same speed on any machine."""
    import torch

    torch.set_num_threads(1)
