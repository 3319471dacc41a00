"""Read a ground-truth bag: the cloud messages (raw CDR kept for replay) and their labels.

Every way a bag can be unusable ends in one ``BagError`` subclass with a one-line message.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
from typing import Any

import numpy as np

from point_gn_ros.bag import (CLASS_NAMES_TOPIC, DEFAULT_TOPIC, GT_FIELD, META_PREFIX,
                              POINTCLOUD2, SEGMENT_FIELD, STRING)
from point_gn_ros.bag.errors import (BagCorruptError, BagError, BagNotFoundError,
                                     EmptyBagError, MissingTopicError, NoGroundTruthError,
                                     WrongTypeError)
from point_gn_ros.errors import DecodeError

# Single-object messages are answered with segment_id -1 (the node's convention).
NO_SEGMENT = -1


@dataclass
class BagMessage:
    """One cloud message: raw bytes for replay, ground truth per object."""

    index: int                    # position on the cloud topic
    log_ns: int                   # recording time (paces replay)
    stamp_ns: int                 # header stamp: the match key
    raw: bytes
    gt: dict[int, int]            # segment id (-1: whole message) -> class index
    points: dict[int, int]        # segment id -> finite point count
    clouds: dict[int, np.ndarray] | None = None   # segment id -> xyz, when asked for


@dataclass
class BagContents:
    path: Path
    topic: str
    storage: str
    class_names: list[str]
    messages: list[BagMessage]
    segmented: bool               # messages carry the `segment` field
    custom: dict[str, str] = field(default_factory=dict)

    @property
    def objects(self) -> int:
        return sum(len(m.gt) for m in self.messages)

    @property
    def rate_hz(self) -> float:
        """Median message rate of the recording (0 for a single message)."""
        if len(self.messages) < 2:
            return 0.0
        gaps = np.diff([m.log_ns for m in self.messages])
        med = float(np.median(gaps))
        return 1e9 / med if med > 0 else 0.0

    def summary(self) -> str:
        return (f'{self.path} ({self.storage}): {len(self.messages)} message(s), '
                f'{self.objects} object(s) on {self.topic}, {len(self.class_names)} classes, '
                f'{self.rate_hz:.1f} Hz' + (', segmented' if self.segmented else ''))


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def _open(path: Path) -> Any:
    from rosbags.rosbag2 import Reader, ReaderError

    if not path.exists():
        raise BagNotFoundError(f'{path}: no such bag')
    try:
        reader = Reader(path)
        reader.open()
    except FileNotFoundError:
        raise BagNotFoundError(f'{path}: not a rosbag2 bag (no metadata.yaml)') from None
    except ReaderError as exc:
        raise BagCorruptError(f'{path}: cannot open the bag, truncated or corrupt? '
                              f'({exc})') from None
    except Exception as exc:  # noqa: BLE001 - sqlite3/mcap/yaml errors on a damaged bag
        raise BagCorruptError(f'{path}: cannot open the bag, truncated or corrupt '
                              f'({type(exc).__name__}: {exc})') from None
    return reader


def _pick_topic(path: Path, topics: dict[str, Any], topic: str | None) -> str:
    listing = ', '.join(f'{t} [{i.msgtype}]' for t, i in sorted(topics.items())) or 'none'
    if topic is not None:
        if topic not in topics:
            raise MissingTopicError(f'{path}: no topic {topic} in the bag (topics: {listing})')
        return topic
    if DEFAULT_TOPIC in topics:
        return DEFAULT_TOPIC
    clouds = [t for t, i in topics.items() if i.msgtype == POINTCLOUD2]
    if len(clouds) == 1:
        return clouds[0]
    if not clouds:
        raise MissingTopicError(f'{path}: no {POINTCLOUD2} topic in the bag (topics: {listing})')
    raise MissingTopicError(f'{path}: several PointCloud2 topics ({", ".join(sorted(clouds))}); '
                            'choose one with --topic')


def read_bag(path: str | os.PathLike[str], topic: str | None = None,
             keep_clouds: bool = False) -> BagContents:
    """Read and check a bag written by ``point_gn bag write`` (or laid out the same way).

    keep_clouds: also keep each object's decoded xyz (for offline classification).
    """
    from rosbags.rosbag2 import ReaderError

    path = Path(path)
    reader = _open(path)
    try:
        topics = reader.topics
        storage = _storage_of(reader)
        cloud_topic = _pick_topic(path, topics, topic)
        msgtype = topics[cloud_topic].msgtype
        if msgtype != POINTCLOUD2:
            raise WrongTypeError(f'{path}: topic {cloud_topic} carries {msgtype}, '
                                 f'expected {POINTCLOUD2}')
        if topics[cloud_topic].msgcount == 0:
            raise EmptyBagError(f'{path}: topic {cloud_topic} has no messages')
        metadata = getattr(reader.storage, 'metadata', None)   # directory bags only
        custom = dict(getattr(metadata, 'custom', None) or {})
        wanted = [c for c in reader.connections if c.topic in (cloud_topic, CLASS_NAMES_TOPIC)]
        typestore = _typestore()
        names_text: str | None = None
        raws: list[tuple[int, bytes]] = []
        try:
            for conn, log_ns, raw in reader.messages(wanted):
                if conn.topic == cloud_topic:
                    raws.append((log_ns, bytes(raw)))
                elif names_text is None and conn.msgtype == STRING:
                    names_text = typestore.deserialize_cdr(raw, STRING).data
        except BagError:
            raise
        except (ReaderError, Exception) as exc:  # noqa: BLE001 - any storage failure
            raise BagCorruptError(f'{path}: truncated or corrupt after {len(raws)} message(s) '
                                  f'on {cloud_topic} ({type(exc).__name__}: {exc})') from None
        expected = topics[cloud_topic].msgcount
        if len(raws) < expected:
            raise BagCorruptError(f'{path}: truncated: read {len(raws)} of the {expected} '
                                  f'messages on {cloud_topic} listed in the metadata')
    finally:
        reader.close()

    if names_text is None:
        names_text = custom.get(META_PREFIX + 'class_names')
    if not names_text:
        raise NoGroundTruthError(f'{path}: no class names ({CLASS_NAMES_TOPIC} topic or '
                                 f'{META_PREFIX}class_names metadata): not a ground-truth bag')
    class_names = names_text.split('\n')
    raws.sort(key=lambda item: item[0])   # storage order is by time already; be sure
    messages, segmented = _decode_all(path, cloud_topic, raws, typestore, len(class_names),
                                      keep_clouds)
    stamps = [m.stamp_ns for m in messages]
    if len(set(stamps)) != len(stamps):
        raise BagError(f'{path}: header stamps on {cloud_topic} are not unique; replay '
                       'matches answers to messages by stamp')
    return BagContents(path, cloud_topic, storage, class_names, messages, segmented, custom)


def _storage_of(reader: Any) -> str:
    files = getattr(reader.storage, 'files', None) or []
    paths = [str(f.get('path', '')) for f in files] if files else []
    if any(p.endswith('.mcap') for p in paths) or reader.path.suffix == '.mcap':
        return 'mcap'
    if any(p.endswith('.db3') for p in paths) or reader.path.suffix == '.db3':
        return 'sqlite3'
    found = {p.suffix for p in reader.path.glob('*')} if reader.path.is_dir() else set()
    return 'mcap' if '.mcap' in found else 'sqlite3' if '.db3' in found else 'unknown'


def _decode_all(path: Path, topic: str, raws: list[tuple[int, bytes]], typestore: Any,
                num_classes: int, keep_clouds: bool) -> tuple[list[BagMessage], bool]:
    from point_gn_ros.pointcloud2 import decode_xyz, split_segments

    messages: list[BagMessage] = []
    segmented = False
    for i, (log_ns, raw) in enumerate(raws):
        try:
            msg = typestore.deserialize_cdr(raw, POINTCLOUD2)
        except Exception as exc:  # noqa: BLE001 - a damaged message body
            raise BagCorruptError(f'{path}: message {i} on {topic} cannot be deserialised '
                                  f'({type(exc).__name__}: {exc})') from None
        names = {f.name for f in msg.fields}
        if GT_FIELD not in names:
            raise NoGroundTruthError(f'{path}: message {i} on {topic} has no {GT_FIELD!r} '
                                     f'field (fields: {", ".join(sorted(names))})')
        has_seg = SEGMENT_FIELD in names
        if i == 0:
            segmented = has_seg
        elif has_seg != segmented:
            raise BagError(f'{path}: message {i} on {topic} '
                           f'{"has" if has_seg else "lacks"} the {SEGMENT_FIELD!r} field '
                           'unlike message 0')
        try:
            extra = (GT_FIELD, SEGMENT_FIELD) if has_seg else (GT_FIELD,)
            decoded = decode_xyz(msg, extra, allow_empty=True)
            if has_seg:
                parts = split_segments(decoded, SEGMENT_FIELD)
                labels = {sid: decoded.fields[GT_FIELD][decoded.fields[SEGMENT_FIELD] == sid]
                          for sid, _ in parts}
            else:
                parts = [(NO_SEGMENT, decoded.xyz)]
                labels = {NO_SEGMENT: decoded.fields[GT_FIELD]}
        except DecodeError as exc:
            raise BagCorruptError(f'{path}: message {i} on {topic}: {exc}') from None
        gt: dict[int, int] = {}
        for sid, lab in labels.items():
            if (sid < 0 and has_seg) or lab.size == 0:
                continue   # the node ignores negative segment ids (background), empty objects
            values = np.unique(lab)
            if len(values) != 1 or not 0 <= int(values[0]) < num_classes:
                raise NoGroundTruthError(f'{path}: message {i} on {topic}: {GT_FIELD} of '
                                         f'segment {sid} is {values[:5].tolist()}, not one '
                                         f'class index in [0, {num_classes})')
            gt[int(sid)] = int(values[0])
        stamp = msg.header.stamp
        messages.append(BagMessage(
            index=i, log_ns=int(log_ns), stamp_ns=stamp.sec * 1_000_000_000 + stamp.nanosec,
            raw=raw, gt=gt, points={int(s): len(x) for s, x in parts if int(s) in gt},
            clouds={int(s): x for s, x in parts if int(s) in gt} if keep_clouds else None))
    return messages, segmented
