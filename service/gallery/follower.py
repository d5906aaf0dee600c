"""Follow the other replicas: keep this one's snapshot in step with the shared store.

One thread per replica, after the gallery has loaded: it reads the store's version and, when
the version has moved, has the catalog load what differs (``Catalog.sync``); then it waits for
a notification (PostgreSQL LISTEN/NOTIFY) or ``poll_s``, whichever comes first, so a missed
notification costs at most ``poll_s``. Each round also tells whether the store can be reached:
``report`` gets the reason while it cannot (the readiness probe's answer), None once it can.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from service.errors import StoreUnavailable
from service.gallery.catalog import Catalog
from service.gallery.encoding import StoreCorrupted

log = logging.getLogger(__name__)


def follow(
    catalog: Catalog,
    poll_s: float,
    stop: threading.Event,
    report: Callable[[str | None], None],
) -> None:
    """Until ``stop`` is set."""
    seen: int | None = None
    problem: str | None = None
    while not stop.is_set():
        try:
            version = catalog.store.version()
            if version != seen:
                catalog.sync()
                seen = version
            if problem is not None:
                log.info("the gallery store is reachable again")
            problem = None
            report(None)
            catalog.store.wait_for_change(poll_s)
        except (StoreUnavailable, StoreCorrupted) as error:
            reason = f"the gallery store cannot be used: {error}"
            if reason != problem:
                log.error("%s; retrying every %s s", reason, poll_s)
            problem = reason
            report(reason)
            stop.wait(poll_s)
        except Exception:  # a bug: logged, and the next round tries again
            log.exception("following the gallery store failed")
            stop.wait(poll_s)
