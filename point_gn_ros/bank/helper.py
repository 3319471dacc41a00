"""One helper thread for the classifier's independent halves of a query's work.

A two-section bank evaluates its scan section there while the caller evaluates the complete
section (bank/classifier.py); a lone query's coarse int8 pass over a large index scans half
of the rows there (bank/search.py). Both are compiled scans that release the GIL, and each
half's result does not depend on which thread computed it. None on a one-CPU machine, and
never used from the helper thread itself (one worker: it would wait for itself).

Each use keeps the helper off the caller's CPU (Linux): woken after an idle gap, it was
queued behind its busy caller on the same CPU for up to a scheduler tick (p90 1.2 ms after
33 ms gaps, against ~50 us back to back) while the other CPU idled. The encoder's helper
for a lone cloud does the same (core/kernels/pgn_lone.c `keep_away`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import ctypes
import os
import threading

from point_gn_ros.core.encoder import default_threads
from point_gn_ros.core.threads import name_os_thread

_NAME = 'pgn_helper'
_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_tid: int | None = None          # the helper's native thread id, once it has started
_cpus: set[int] = set()          # the CPUs this process may use (when the helper started)
_away_from = -1                  # the CPU the helper was last kept off


try:
    _sched_getcpu = ctypes.CDLL(None).sched_getcpu
    _sched_getcpu.restype = ctypes.c_int
    _sched_getcpu.argtypes = []
except (AttributeError, OSError):     # not glibc / not Linux: the helper stays where it is
    _sched_getcpu = None


def _keep_away() -> None:
    """Pin the helper to this process's CPUs other than the caller's (under _lock)."""
    global _away_from
    if _tid is None or _sched_getcpu is None:
        return
    cpu = _sched_getcpu()   # -1 on failure
    if cpu < 0 or cpu == _away_from or cpu not in _cpus or len(_cpus) < 2:
        return
    try:
        os.sched_setaffinity(_tid, _cpus - {cpu})
        _away_from = cpu
    except OSError:                      # the thread is gone, or a cpuset forbids it
        pass


def _forget_in_child() -> None:
    """A forked child has no helper thread: start its own on first use."""
    global _pool, _tid, _away_from, _lock
    _pool, _tid, _away_from, _lock = None, None, -1, threading.Lock()


if hasattr(os, 'register_at_fork'):
    os.register_at_fork(after_in_child=_forget_in_child)


def helper_thread() -> ThreadPoolExecutor | None:
    """The helper (started on first use), or None: one usable CPU, or called from it."""
    global _pool, _tid, _cpus
    if threading.current_thread().name.startswith(_NAME):
        return None
    with _lock:
        if _pool is None and default_threads() > 1:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=_NAME,
                                       initializer=name_os_thread)
            if hasattr(os, 'sched_setaffinity'):
                _cpus = set(os.sched_getaffinity(0))
                _tid = _pool.submit(threading.get_native_id).result()
        if _pool is not None:
            _keep_away()
        return _pool
