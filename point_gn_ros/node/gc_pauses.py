"""Keep Python's full garbage collections off the answer path (ROS-free).

A configured node holds ~185,000 objects the cyclic collector tracks (torch, numpy, rclpy,
the bank's metadata), none of which is ever garbage. Every few hundred messages a full
(generation 2) collection walks all of them: ~100 ms holding the GIL, so the worker and the
executor both stall and a handful of answers arrive late (`benchmarks/node_path_time.py` under
a gc callback: a 90 ms pause in 900 messages). `gc.freeze()` moves what exists once the node
is configured into a permanent generation the collector skips; what is created later
(messages, answers, enrolled banks) is collected normally, and reference counting frees
frozen objects as usual. `thaw()` gives them back at cleanup, so the bank a reconfigure
replaces can still be collected.
"""

from __future__ import annotations

import gc


def freeze_startup_objects() -> int:
    """Collect once, then freeze every tracked object; -> how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def thaw() -> None:
    """Give frozen objects back to the collector (a later freeze takes them again)."""
    gc.unfreeze()
