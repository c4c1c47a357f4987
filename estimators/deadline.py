"""The instant after which an estimator must not start a search of the whole frame.

An estimator given a prior tracks from it; when the track fails it falls back to a search of
the whole frame (acquisition, 100–250 ms). On the wall clock a fused estimate's frame is worth
acting on only while it is younger than ``vision.max_frame_age_s``: a search that ends later is
thrown away, and it holds a core the other systems need meanwhile. The vision worker therefore
runs each estimate under the deadline the pipeline gives it, and the estimators ask
``search_allowed()`` before falling back. Outside such a context (tests, open-loop evaluation,
``--clock sim`` with its modelled times) there is no deadline and nothing changes.

The deadline is on ``time.monotonic`` (system-wide, so the vision process that sets it and the
worker that checks it agree).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

_search_deadline: ContextVar[float | None] = ContextVar("search_deadline", default=None)


@contextmanager
def search_deadline(deadline: float | None) -> Iterator[None]:
    """Within the block, a search may start only until ``deadline`` (None: any time)."""
    token = _search_deadline.set(deadline)
    try:
        yield
    finally:
        _search_deadline.reset(token)


def search_allowed() -> bool:
    """Whether a search of the whole frame may still start."""
    deadline = _search_deadline.get()
    return deadline is None or time.monotonic() <= deadline


#: What a measurement says when its track failed and the search was not started.
NO_TIME_FOR_SEARCH = "no search: its result would come too late to act on"
