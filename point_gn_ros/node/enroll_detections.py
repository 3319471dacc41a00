"""The ~/enroll route's ROS-free parts: pair detection arrays with scene clouds, crop boxes.

node/enrollment.py feeds these: each vision_msgs/Detection3DArray waits for the scene
PointCloud2 of the same header stamp (`StampPairing`), then each detection's box crops one
example out of that cloud (`crop_box`).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

__all__ = ['StampPairing', 'crop_box']


class StampPairing:
    """Matches detection arrays with scene clouds of the identical header stamp.

    Either may arrive first; one left alone longer than `timeout_s`, or pushed out as the
    oldest of more than `max_waiting` on its side, is discarded and counted in `expired`.
    Thread-safe.
    """

    def __init__(self, timeout_s: float, max_waiting: int = 16) -> None:
        self.timeout_s = timeout_s
        self.max_waiting = max_waiting
        self.expired = 0
        self._waiting: tuple[dict, dict] = ({}, {})      # detections, scenes: key -> (t, msg)
        self._lock = threading.Lock()

    def add(self, dets: Any, scene: Any) -> list[tuple[Any, Any]]:
        """Give one message (the other None); -> [(detections, scene)] pairs now complete."""
        msg = dets if dets is not None else scene
        side = 0 if dets is not None else 1
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        now = time.monotonic()
        with self._lock:
            for waiting in self._waiting:
                for k in [k for k, (t, _) in waiting.items() if now - t > self.timeout_s]:
                    del waiting[k]
                    self.expired += 1
            other = self._waiting[1 - side].pop(key, None)
            if other is None:
                mine = self._waiting[side]
                mine[key] = (now, msg)
                while len(mine) > self.max_waiting:      # insertion order: oldest first
                    del mine[next(iter(mine))]
                    self.expired += 1
                return []
        return [(msg, other[1]) if side == 0 else (other[1], msg)]


def crop_box(xyz: np.ndarray, bbox: Any) -> np.ndarray:
    """Points of xyz (N, 3) inside a vision_msgs/BoundingBox3D -> (M, 3) float32.

    The box is in the cloud's frame (centre pose + size); a box of size 0 keeps every point
    (the whole scene is the example).
    """
    size = np.array([bbox.size.x, bbox.size.y, bbox.size.z], dtype=np.float64)
    if not (size > 0).any():
        return xyz
    c = bbox.center.position
    q = bbox.center.orientation
    rot = _quat_matrix(q.x, q.y, q.z, q.w)                # box axes in the cloud frame
    local = (xyz.astype(np.float64) - np.array([c.x, c.y, c.z])) @ rot
    inside = (np.abs(local) <= size / 2 + 1e-6).all(axis=1)
    return xyz[inside]


def _quat_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """(3, 3) rotation of a quaternion (identity for the all-zero default)."""
    n = x * x + y * y + z * z + w * w
    if n < 1e-12:
        return np.eye(3)
    s = 2.0 / n
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)]])
