"""Seconds spent in each stage of training, summed: the account of where the time goes.

Every process of the actor-replay-learner path keeps one and hands its sums on with what it already
returns (``benchmarks/where_time_goes.py`` reads them). A stage costs two ``perf_counter`` calls,
under a microsecond, against stages of a millisecond or more, so the clock is always on.
"""

from __future__ import annotations

import pickle
import time
from collections import defaultdict
from contextlib import contextmanager


class Stopwatch:
    def __init__(self):
        self.seconds: defaultdict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - start

    def pop(self) -> dict[str, float]:
        """The sums since the last ``pop``, and start again from zero."""
        out, self.seconds = dict(self.seconds), defaultdict(float)
        return out


def add_seconds(total: dict[str, float], more: dict[str, float]) -> dict[str, float]:
    for stage, seconds in more.items():
        total[stage] = total.get(stage, 0.0) + seconds
    return total


def with_size(answer: dict) -> dict:
    """``answer`` with ``bytes``: its pickled size, measured by the process that sends it, so that the receiver (the
    driver) accounts for the bytes it takes in without pickling them again."""
    answer["bytes"] = len(pickle.dumps(answer))
    return answer
