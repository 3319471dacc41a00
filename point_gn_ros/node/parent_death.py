"""Stop the node when the process that launched it dies (Linux): `kill -TERM` on launch.

`ros2 launch` stops its processes on SIGINT, but on SIGTERM it exits at once and leaves them
running (launch's own warning: "using SIGTERM can result in orphaned processes"). The launch
file sets POINT_GN_EXIT_WITH_PARENT=1; the node then asks the kernel for a SIGTERM when its
parent exits (prctl PR_SET_PDEATHSIG), which rclpy turns into a clean shutdown.
"""

from __future__ import annotations

import os
import signal
import sys

ENV = 'POINT_GN_EXIT_WITH_PARENT'
_PR_SET_PDEATHSIG = 1


def exit_with_parent() -> bool:
    """Arrange SIGTERM on the parent's death when ENV is '1' (Linux); True when arranged."""
    if os.environ.get(ENV) != '1' or not sys.platform.startswith('linux'):
        return False
    import ctypes
    parent = os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        return False
    if os.getppid() != parent:           # it died before the request: the signal never comes
        os.kill(os.getpid(), signal.SIGTERM)
    return True
