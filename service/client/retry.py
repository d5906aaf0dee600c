"""When and how long the client sends an idempotent call again: on a connection error, a 502
(a proxy whose replica died mid-request) or a 503 (the service loading, busy, or its gallery's
database out of reach), with exponential backoff and jitter, within a bounded total time.

Only calls that give the same outcome however often they arrive are retried: alignments and
reads change nothing, and a registration of the same points under the same name is answered
``200 identical`` once it is stored (never ``409``), so a registration whose first answer was
lost is safe to send again. A deletion is retried too; a ``404`` to a retry of a deletion whose
earlier attempt may have reached the service counts as done (docs/operations.md, "Failures").
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass

RETRY_STATUSES = frozenset({502, 503})


@dataclass(frozen=True)
class Retry:
    """``total_s``: no attempt starts later than this after the first (0: never retry);
    waits start at ``first_delay_s`` and double up to ``max_delay_s``, each drawn between
    half and all of that (so that clients that failed together do not retry together); a
    ``Retry-After`` the service sends is waited for instead, within the same bound."""

    total_s: float = 30.0
    first_delay_s: float = 0.2
    max_delay_s: float = 3.0

    def waits(self) -> Waits:
        return Waits(self)


class Waits:
    """One call's sequence of waits: ``next(retry_after)`` is how long to sleep before the
    next attempt, or None once the total time would be passed."""

    def __init__(self, policy: Retry, clock: Callable[[], float] = time.monotonic):
        self.policy = policy
        self.clock = clock
        self.deadline = clock() + policy.total_s
        self.delay = policy.first_delay_s
        self.attempts = 1

    def next(self, retry_after: float | None = None) -> float | None:
        wait = self.delay * random.uniform(0.5, 1.0)
        if retry_after is not None:
            wait = min(retry_after, self.policy.max_delay_s)
        if self.policy.total_s <= 0 or self.clock() + wait > self.deadline:
            return None
        self.delay = min(self.delay * 2, self.policy.max_delay_s)
        self.attempts += 1
        return wait
