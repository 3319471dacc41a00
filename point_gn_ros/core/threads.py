"""OS-visible names for this package's threads, so `top -H` and `ps -L` tell them apart.

Python (before 3.14) names only its own Thread objects; the OS sees every thread as
"python". On Linux each thread body calls `name_os_thread()` first, as the C kernels'
helper does with pthread_setname_np ("pgn_enc_helper"); elsewhere it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading

_PR_SET_NAME = 15          # linux/prctl.h
_MAX_NAME = 15             # the kernel's 16 bytes, NUL included


def name_os_thread(name: str | None = None) -> bool:
    """Give the calling thread `name` (default: its threading name) in the OS; True if done."""
    if not sys.platform.startswith('linux'):
        return False
    text = (name or threading.current_thread().name).encode('ascii', 'replace')[:_MAX_NAME]
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_NAME, text, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


# Niceness of background threads that rebuild what answers use (enrollment commits, ridge
# refits): the threads that answer get the CPU first.
BACKGROUND_NICE = 10


def lower_priority(nice: int = BACKGROUND_NICE) -> bool:
    """Make the calling thread `nice` (Linux: per thread); True if done."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except (AttributeError, OSError):
        return False              # not Linux, or not allowed: the default priority
    return True


def trim_heap() -> bool:
    """Give the C heap's free memory back to the OS (glibc `malloc_trim`); True if done.

    A background thread that builds and drops large buffers (a bank version, a ridge refit)
    leaves them free in its own malloc arena, which glibc keeps. Teaching 100 classes to the
    default bank grew the node's RSS by 1.1-1.3 GB without this, 0.9 GB with it (one run);
    fragmentation across arenas keeps the rest (MALLOC_ARENA_MAX=2: 0.3 GB, docs/NODE.md).
    """
    if not sys.platform.startswith('linux'):
        return False
    try:
        return bool(ctypes.CDLL(None).malloc_trim(0))
    except (OSError, AttributeError):
        return False
