"""RViz markers for classified objects: a "label score" text above each and its bounding box.

Per input topic the markers live in their own namespaces (`<topic>/labels`,
`<topic>/boxes`) with ids 0..n-1; when a message yields fewer objects than the
previous one on that topic, the now unused ids get DELETE actions, so RViz never
shows stale objects and the other topics' markers are left alone (a DELETEALL
would wipe every namespace of the display).
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from typing import Any
from collections.abc import Sequence

import numpy as np

# Text height (m) and how far above the box top it floats, as a fraction of the box height.
TEXT_HEIGHT = 0.12
TEXT_LIFT = 0.15
BOX_LINE_WIDTH = 0.01

# Edges of a box as pairs of corner indices; corner i has bits (x, y, z) = (i & 1, i & 2, i & 4).
_BOX_EDGES = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7),
              (0, 4), (1, 5), (2, 6), (3, 7))


@dataclass(frozen=True)
class ObjectBox:
    """Axis-aligned bounds (input frame) and result of one classified object."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    label: str
    class_id: int
    score: float


def object_box(xyz: np.ndarray, label: str, class_id: int, score: float) -> ObjectBox:
    """ObjectBox of an (N, 3) cloud."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    return ObjectBox(tuple(float(v) for v in lo), tuple(float(v) for v in hi), label,
                     int(class_id), float(score))


def class_colour(class_id: int) -> tuple[float, float, float]:
    """A stable, well-spread RGB colour per class id; grey for unknown (-1)."""
    if class_id < 0:
        return (0.6, 0.6, 0.6)
    hue = (class_id * 0.618033988749895) % 1.0     # golden-ratio steps spread hues evenly
    return colorsys.hsv_to_rgb(hue, 0.85, 1.0)


def box_corners(lo: Sequence[float], hi: Sequence[float]) -> list[tuple[float, float, float]]:
    return [(hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1], hi[2] if i & 4 else lo[2])
            for i in range(8)]


def box_line_points(lo: Sequence[float], hi: Sequence[float]) -> list[tuple[float, float, float]]:
    """The 24 LINE_LIST points (12 edges) of an axis-aligned box."""
    c = box_corners(lo, hi)
    return [c[i] for edge in _BOX_EDGES for i in edge]


class MarkerTracker:
    """Builds each topic's MarkerArray and remembers how many objects it showed last time."""

    def __init__(self, topics: Sequence[str]) -> None:
        self._ns = [t.strip('/').replace('/', '_') or f'topic{i}' for i, t in enumerate(topics)]
        self._previous = [0] * len(topics)

    def namespaces(self, topic_index: int) -> tuple[str, str]:
        base = self._ns[topic_index]
        return f'{base}/labels', f'{base}/boxes'

    def build(self, topic_index: int, header: Any, boxes: Sequence[ObjectBox],
              lifetime_s: float = 0.0) -> Any:
        """visualization_msgs/MarkerArray for one answered message (same header).

        lifetime_s: how long RViz shows them unless replaced (0 = until replaced), so that
        objects vanish when the node stops answering.
        """
        from builtin_interfaces.msg import Duration
        from geometry_msgs.msg import Point
        from visualization_msgs.msg import Marker, MarkerArray

        ns = int(round(max(lifetime_s, 0.0) * 1e9))
        lifetime = Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

        text_ns, box_ns = self.namespaces(topic_index)
        out = MarkerArray()
        for i, b in enumerate(boxes):
            r, g, bl = class_colour(b.class_id)
            size = max(hi - lo for lo, hi in zip(b.lo, b.hi, strict=True))
            text = Marker()
            text.header = header
            text.ns, text.id = text_ns, i
            text.type, text.action = Marker.TEXT_VIEW_FACING, Marker.ADD
            text.pose.position.x = (b.lo[0] + b.hi[0]) / 2
            text.pose.position.y = (b.lo[1] + b.hi[1]) / 2
            text.pose.position.z = b.hi[2] + TEXT_LIFT * max(size, 0.1) + TEXT_HEIGHT / 2
            text.pose.orientation.w = 1.0
            text.scale.z = TEXT_HEIGHT
            text.color.r, text.color.g, text.color.b, text.color.a = 1.0, 1.0, 1.0, 1.0
            text.text = f'{b.label} {b.score:.2f}'
            text.lifetime = lifetime
            box = Marker()
            box.header = header
            box.ns, box.id = box_ns, i
            box.type, box.action = Marker.LINE_LIST, Marker.ADD
            box.pose.orientation.w = 1.0
            box.scale.x = BOX_LINE_WIDTH
            box.color.r, box.color.g, box.color.b, box.color.a = float(r), float(g), float(bl), 1.0
            box.points = [Point(x=p[0], y=p[1], z=p[2]) for p in box_line_points(b.lo, b.hi)]
            box.lifetime = lifetime
            out.markers += [text, box]
        for i in range(len(boxes), self._previous[topic_index]):
            for ns in (text_ns, box_ns):
                gone = Marker()
                gone.header = header
                gone.ns, gone.id, gone.action = ns, i, Marker.DELETE
                out.markers.append(gone)
        self._previous[topic_index] = len(boxes)
        return out
