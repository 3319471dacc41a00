"""Write a dataset split as a rosbag2 bag of PointCloud2 messages with ground truth.

Serialisation goes through the ``rosbags`` Jazzy typestore, so writing needs no ROS install.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import time
from typing import Any, Protocol

import numpy as np

from point_gn_ros.bag import (CLASS_NAMES_TOPIC, DEFAULT_TOPIC, GT_FIELD, META_PREFIX,
                              POINTCLOUD2, SEGMENT_FIELD, STRING)
from point_gn_ros.bag.errors import BagError
from point_gn_ros.bag.realism import Realism

STORAGES = ('mcap', 'sqlite3')
# Where non-sensor-frame objects of one message go: side by side along x (dataset units).
SIDE_BY_SIDE_STEP = 2.5
# sensor_msgs/PointField datatypes.
_INT32, _FLOAT32 = 5, 7


class DatasetLike(Protocol):
    """The part of the Dataset contract the writer uses."""

    class_names: list[str]

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]: ...


@dataclass(frozen=True)
class WriteOptions:
    """How to turn a dataset into a bag (see ``point_gn bag write --help``)."""

    storage: str = 'mcap'
    rate_hz: float = 10.0
    objects_per_message: int = 1
    topic: str = DEFAULT_TOPIC
    limit: int | None = None
    frame_id: str = 'sensor'
    realism: Realism = field(default_factory=Realism)
    seed: int = 0
    start_ns: int | None = None   # first header stamp; None = now (like a fresh recording)

    def check(self) -> None:
        if self.storage not in STORAGES:
            raise BagError(f'--storage must be one of {", ".join(STORAGES)} '
                           f'(got {self.storage!r})')
        if not (self.rate_hz > 0 and np.isfinite(self.rate_hz)):
            raise BagError(f'--rate must be > 0 Hz (got {self.rate_hz})')
        if self.objects_per_message < 1:
            raise BagError(f'--objects-per-message must be >= 1 (got {self.objects_per_message})')
        if self.limit is not None and self.limit < 1:
            raise BagError(f'--limit must be >= 1 (got {self.limit})')
        if not self.topic.startswith('/') or self.topic == CLASS_NAMES_TOPIC:
            raise BagError(f'--topic must be an absolute topic name other than '
                           f'{CLASS_NAMES_TOPIC} (got {self.topic!r})')


@dataclass
class WriteSummary:
    path: Path
    storage: str
    topic: str
    messages: int
    objects: int
    points: int
    duration_s: float
    seconds_taken: float

    def line(self) -> str:
        return (f'wrote {self.path} ({self.storage}): {self.messages} message(s), '
                f'{self.objects} object(s), {self.points:,} points on {self.topic}, '
                f'{self.duration_s:.1f} s of recording (written in {self.seconds_taken:.1f} s)')


def pack_cloud(typestore: Any, stamp_ns: int, frame_id: str, xyz: np.ndarray,
               labels: np.ndarray, segments: np.ndarray | None) -> Any:
    """A rosbags PointCloud2: FLOAT32 x, y, z, INT32 gt_label [, INT32 segment], packed LE."""
    t = typestore.types
    names = ['x', 'y', 'z', GT_FIELD] + ([SEGMENT_FIELD] if segments is not None else [])
    dtype = np.dtype({'names': names, 'formats': ['<f4'] * 3 + ['<i4'] * (len(names) - 3)})
    rec = np.empty(len(xyz), dtype=dtype)
    rec['x'], rec['y'], rec['z'] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec[GT_FIELD] = labels
    if segments is not None:
        rec[SEGMENT_FIELD] = segments
    fields = [t['sensor_msgs/msg/PointField'](name=n, offset=4 * i,
                                              datatype=_FLOAT32 if i < 3 else _INT32, count=1)
              for i, n in enumerate(names)]
    stamp = t['builtin_interfaces/msg/Time'](sec=stamp_ns // 1_000_000_000,
                                             nanosec=stamp_ns % 1_000_000_000)
    return t[POINTCLOUD2](
        header=t['std_msgs/msg/Header'](stamp=stamp, frame_id=frame_id),
        height=1, width=len(xyz), fields=fields, is_bigendian=False,
        point_step=dtype.itemsize, row_step=dtype.itemsize * len(xyz),
        data=rec.view(np.uint8).reshape(-1), is_dense=True)


def _latched_qos() -> list[Any]:
    """Offered QoS for the class-names topic, so that ``ros2 bag play`` offers it latched."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def _object_rng(seed: int, index: int) -> np.random.Generator:
    # One stream per object: --limit or --objects-per-message never change an object's view.
    return np.random.default_rng([seed, index])


def write_bag(dataset: DatasetLike, out: str | os.PathLike[str], opts: WriteOptions,
              source: str = '', progress: bool = False) -> WriteSummary:
    """Write `dataset` (first `opts.limit` objects) to a new bag directory `out`."""
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    opts.check()
    out = Path(out)
    if out.exists():
        raise BagError(f'{out}: already exists; remove it or choose another -o')
    names = list(dataset.class_names)
    total = len(dataset) if opts.limit is None else min(opts.limit, len(dataset))
    if total == 0:
        raise BagError(f'{source or "dataset"}: no objects to write')
    typestore = get_typestore(Stores.ROS2_JAZZY)
    start_ns = time.time_ns() if opts.start_ns is None else int(opts.start_ns)
    period_ns = max(1, round(1e9 / opts.rate_hz))
    t0 = time.perf_counter()
    plugin = StoragePlugin.MCAP if opts.storage == 'mcap' else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=plugin)
    meta = {'class_names': '\n'.join(names), 'source': source,
            'objects_per_message': str(opts.objects_per_message), 'topic': opts.topic,
            'rate_hz': f'{opts.rate_hz:g}', 'seed': str(opts.seed),
            'realism': json.dumps(opts.realism.as_dict()), 'gt_field': GT_FIELD}
    for key, value in meta.items():
        writer.set_custom_data(META_PREFIX + key, value)

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, desc='writing', unit='object')
    messages = points = 0
    try:
        writer.open()
        names_conn = writer.add_connection(CLASS_NAMES_TOPIC, STRING, typestore=typestore,
                                           offered_qos_profiles=_latched_qos())
        cloud_conn = writer.add_connection(opts.topic, POINTCLOUD2, typestore=typestore)
        names_msg = typestore.types[STRING](data='\n'.join(names))
        # Just before the first cloud, so that a player delivers it first.
        writer.write(names_conn, start_ns - 1, typestore.serialize_cdr(names_msg, STRING))
        per = opts.objects_per_message
        for first in range(0, total, per):
            idx = range(first, min(first + per, total))
            xyz, labels, segments = _message_points(dataset, idx, opts, len(names))
            stamp_ns = start_ns + messages * period_ns
            msg = pack_cloud(typestore, stamp_ns, opts.frame_id, xyz, labels,
                             segments if per > 1 else None)
            writer.write(cloud_conn, stamp_ns, typestore.serialize_cdr(msg, POINTCLOUD2))
            messages += 1
            points += len(xyz)
            if bar is not None:
                bar.update(len(idx))
        writer.close()
    except WriterError as exc:
        writer.abort()
        raise BagError(f'{out}: cannot write the bag ({exc})') from None
    except BaseException:
        writer.abort()
        raise
    finally:
        if bar is not None:
            bar.close()
    return WriteSummary(out, opts.storage, opts.topic, messages, total, points,
                        (messages - 1) * period_ns / 1e9, time.perf_counter() - t0)


def _message_points(dataset: DatasetLike, idx: Sequence[int], opts: WriteOptions,
                    num_classes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate the (transformed) objects of one message: xyz, gt_label, segment."""
    clouds, labels, segments = [], [], []
    for seg, i in enumerate(idx):
        xyz, label = dataset[i]
        label = int(label)
        if not 0 <= label < num_classes:
            raise BagError(f'object {i} has label {label}, outside the {num_classes} classes')
        xyz = np.asarray(xyz, dtype=np.float32)
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
        if len(xyz) == 0:
            raise BagError(f'object {i} has no finite points')
        xyz = opts.realism.apply(xyz, _object_rng(opts.seed, i))
        if not opts.realism.sensor_frame and len(idx) > 1:
            xyz = xyz + np.float32([SIDE_BY_SIDE_STEP * seg, 0.0, 0.0])
        clouds.append(xyz)
        labels.append(np.full(len(xyz), label, np.int32))
        segments.append(np.full(len(xyz), seg, np.int32))
    return np.concatenate(clouds), np.concatenate(labels), np.concatenate(segments)
