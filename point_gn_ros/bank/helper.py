"""One helper thread for the classifier's independent halves of a query's work.

A two-section bank evaluates its scan section there while the caller evaluates the complete
section (bank/classifier.py); a lone query's coarse int8 pass over a large index scans half
of the rows there (bank/search.py). Both are compiled scans that release the GIL, and each
half's result does not depend on which thread computed it. None on a one-CPU machine, and
never used from the helper thread itself (one worker: it would wait for itself).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import threading

from point_gn_ros.core.encoder import default_threads

_NAME = 'pgn_helper'
_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()


def helper_thread() -> ThreadPoolExecutor | None:
    """The helper (started on first use), or None: one usable CPU, or called from it."""
    global _pool
    if threading.current_thread().name.startswith(_NAME):
        return None
    with _lock:
        if _pool is None and default_threads() > 1:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=_NAME)
        return _pool
