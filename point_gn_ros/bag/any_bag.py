"""Classify every PointCloud2 message of any rosbag2 bag (no ground truth needed).

`read_clouds` takes the chosen PointCloud2 topics (default: all of them) of an mcap or sqlite3
bag, raw CDR kept. `classify_offline` answers them with the core library as the node does
(same decoder, segment split, 'no segment' ids, min_points); `classify_live` publishes them
to the running classifier node at the recorded rate and collects its answers, matched by
(header stamp, frame) in send order, since several messages (one cloud per cluster) may
share a scan's stamp. Either gives one `ObjectAnswer` per object, written to JSON / CSV
(`write_answers`), summarised (`summarise`), and optionally to a new bag beside the inputs
(`write_output_bag`).
"""

from __future__ import annotations

from collections import Counter, defaultdict, deque
import csv
from dataclasses import asdict, dataclass, field
import json
import os
from pathlib import Path
import threading
import time
from typing import Any

import numpy as np

from point_gn_ros.bag import DEFAULT_MIN_POINTS, POINTCLOUD2
from point_gn_ros.bag.errors import (BagCorruptError, EmptyBagError, MissingTopicError,
                                     ReplayError)
from point_gn_ros.bag.reader import _open, _storage_of, _typestore
from point_gn_ros.errors import DecodeError

BATCH = 32                    # the node's default max_batch
CLASSIFICATIONS_TOPIC = '/point_gn/classifications'   # offline answers in an output bag


@dataclass
class CloudMessage:
    """One PointCloud2 message of the bag (raw CDR for publishing)."""

    index: int
    topic: str
    log_ns: int
    stamp_ns: int
    frame_id: str
    raw: bytes


@dataclass
class ObjectAnswer:
    """One classified object: what the JSON and CSV rows hold."""

    message: int                  # CloudMessage.index
    stamp_ns: int
    topic: str
    frame_id: str
    segment: int                  # -1: the whole message is one object
    label: str                    # class name, 'unknown' for class id -1
    class_id: int
    score: float
    topk: list[tuple[str, float]] = field(default_factory=list)
    latency_ms: float | None = None   # publish -> answer (live), else None
    centroid: tuple[float, float, float] = (0.0, 0.0, 0.0)   # input frame


@dataclass
class BagClouds:
    path: Path
    storage: str
    topics: list[str]
    messages: list[CloudMessage]


def read_clouds(path: str | os.PathLike[str], topics: list[str] | None = None) -> BagClouds:
    """The bag's PointCloud2 messages on `topics` (default: every PointCloud2 topic)."""
    path = Path(path)
    reader = _open(path)
    try:
        info = reader.topics
        listing = ', '.join(f'{t} [{i.msgtype}]' for t, i in sorted(info.items())) or 'none'
        clouds = sorted(t for t, i in info.items() if i.msgtype == POINTCLOUD2)
        chosen = list(dict.fromkeys(topics)) if topics else clouds
        if not chosen:
            raise MissingTopicError(f'{path}: no {POINTCLOUD2} topic in the bag (topics: '
                                    f'{listing})')
        for topic in chosen:
            if topic not in info:
                raise MissingTopicError(f'{path}: no topic {topic} in the bag (topics: '
                                        f'{listing})')
            if info[topic].msgtype != POINTCLOUD2:
                raise MissingTopicError(f'{path}: topic {topic} carries {info[topic].msgtype}, '
                                        f'not {POINTCLOUD2}')
        storage = _storage_of(reader)
        typestore = _typestore()
        messages: list[CloudMessage] = []
        try:
            for conn, log_ns, raw in reader.messages(
                    [c for c in reader.connections if c.topic in chosen]):
                msg = typestore.deserialize_cdr(raw, POINTCLOUD2)
                stamp = msg.header.stamp
                messages.append(CloudMessage(len(messages), conn.topic, int(log_ns),
                                             stamp.sec * 1_000_000_000 + stamp.nanosec,
                                             msg.header.frame_id, bytes(raw)))
        except Exception as exc:  # noqa: BLE001 - any storage or CDR failure
            raise BagCorruptError(f'{path}: truncated or corrupt after {len(messages)} '
                                  f'message(s) ({type(exc).__name__}: {exc})') from None
    finally:
        reader.close()
    if not messages:
        raise EmptyBagError(f'{path}: no messages on {", ".join(chosen)}')
    messages.sort(key=lambda m: (m.log_ns, m.index))
    for i, m in enumerate(messages):
        m.index = i
    return BagClouds(path, storage, chosen, messages)


def _name(class_names: list[str], cid: int) -> str:
    return class_names[cid] if 0 <= cid < len(class_names) else 'unknown'


def _rows(m: CloudMessage, segments: list[int], res: Any, class_names: list[str],
          latency_ms: float | None) -> list[ObjectAnswer]:
    out = []
    for j, seg in enumerate(segments):
        cid = int(res['class_id'][j])
        out.append(ObjectAnswer(
            m.index, m.stamp_ns, m.topic, m.frame_id, int(seg), _name(class_names, cid), cid,
            float(res['score'][j]),
            [(_name(class_names, int(c)), float(s))
             for c, s in zip(res['topk_ids'][j], res['topk_scores'][j], strict=True)],
            latency_ms, tuple(round(float(v), 4) for v in res['centroid'][j])))
    return out


def classify_offline(bag: BagClouds, bank: str | None = None, device: str = 'cpu',
                     unknown_threshold: float | None = None,
                     min_points: int = DEFAULT_MIN_POINTS, segment_field: str = '',
                     no_segment_ids: tuple[str, ...] = ('negative', 'max'), up_axis: str = 'auto',
                     top_k: int = 5, metric_size: bool = True
                     ) -> tuple[list[ObjectAnswer], list[str], dict[str, int]]:
    """Every object of the bag's messages, classified as the node would (no ROS graph).

    segment_field: '' = each message one object; a message without that field is one object
    too. Returns (answers, class names, rejected messages by reason).
    """
    from point_gn_ros.node.frames import UpConvention, to_z_up
    from point_gn_ros.node.params import NoSegment
    from point_gn_ros.pointcloud2 import decode_xyz, split_segments
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.as_node(bank, device=device, top_k=top_k,
                             unknown_threshold=unknown_threshold or None, metric_size=metric_size)
    names = list(rec.class_names)
    typestore = _typestore()
    unseg = NoSegment.parse(no_segment_ids)
    up = UpConvention(up_axis)
    rejected: Counter[str] = Counter()
    objects: list[tuple[CloudMessage, int, np.ndarray]] = []
    for m in bag.messages:
        msg = typestore.deserialize_cdr(m.raw, POINTCLOUD2)
        has_field = bool(segment_field) and any(f.name == segment_field for f in msg.fields)
        try:
            decoded = decode_xyz(msg, (segment_field,) if has_field else (), allow_empty=True)
            parts = (split_segments(decoded, segment_field, skip_ids=unseg.ids,
                                    skip_negative=unseg.negative, skip_type_max=unseg.type_max)
                     if has_field else [(-1, decoded.xyz)])
        except DecodeError as exc:
            rejected[str(exc).split(':')[0]] += 1
            continue
        kept = [(seg, xyz) for seg, xyz in parts if len(xyz) >= min_points]
        if not kept and not has_field:
            rejected['too few points'] += 1
        objects += [(m, seg, xyz) for seg, xyz in kept]
    answers: list[ObjectAnswer] = []
    for start in range(0, len(objects), BATCH):
        chunk = objects[start:start + BATCH]
        res = rec.classify_clouds([to_z_up(xyz, up(m.frame_id)) for m, _, xyz in chunk])
        for j, (m, seg, xyz) in enumerate(chunk):
            one = {'class_id': [res.labels[j]], 'score': [res.scores[j]],
                   'topk_ids': [res.topk_ids[j]], 'topk_scores': [res.topk_scores[j]],
                   'centroid': [xyz.mean(axis=0, dtype=np.float64)]}
            answers += _rows(m, [seg], one, names, None)
    return answers, names, dict(rejected)


def classify_live(bag: BagClouds, node_name: str | None = None, rate: float = 1.0,
                  timeout: float = 10.0, discovery_timeout: float = 60.0,
                  log: Any = print) -> tuple[list[ObjectAnswer], list[str], dict[str, Any]]:
    """Publish the bag's clouds to the running node (rate x recorded) and collect its answers.

    Returns (answers, class names, info: sent / answered messages, the node's name, the
    answer messages with their bag times for an output bag).
    """
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from point_gn_ros.bag.replay import _Graph, node_fqn
    from point_gn_ros.pointcloud2 import decode_classifications

    if not (rate > 0 and np.isfinite(rate)):
        raise ReplayError(f'--rate must be > 0 (got {rate})')
    graph = _Graph()
    lock = threading.Condition()
    # (stamp, frame) -> indices of sent messages not answered yet, in send order
    waiting: dict[tuple[int, str], deque[int]] = defaultdict(deque)
    sent_at: dict[int, float] = {}
    got: dict[int, tuple[Any, float]] = {}
    names: list[str] = []
    extra = Counter()
    try:
        node = graph.node
        # Reliable: matches a reliable or best-effort (or 'auto') subscription.
        pubs = {t: node.create_publisher(PointCloud2, t, QoSProfile(
            depth=50, reliability=ReliabilityPolicy.RELIABLE)) for t in bag.topics}
        end = time.monotonic() + discovery_timeout
        fqn = node_fqn(node_name) if node_name else None
        log(f'waiting for the classifier node on {", ".join(bag.topics)}')
        while time.monotonic() < end:
            if fqn is None:
                fqn = next((f for t in bag.topics for f in graph.find_classifiers(t)), None)
            if fqn is not None and all(p.get_subscription_count() > 0 for p in pubs.values()):
                break
            time.sleep(0.05)
        else:
            raise ReplayError(f'no classifier node subscribed to {", ".join(bag.topics)} '
                              f'within {discovery_timeout:g} s (ROS_DOMAIN_ID='
                              f'{os.environ.get("ROS_DOMAIN_ID", "0")}): is it running, with '
                              'these input_topics?')

        def on_answer(msg: Any) -> None:
            t = time.monotonic()
            key = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec,
                   msg.header.frame_id)
            with lock:
                queue = waiting.get(key)
                if not queue:
                    extra['unmatched'] += 1
                    return
                got[queue.popleft()] = (msg, t)
                lock.notify_all()

        def on_names(msg: Any) -> None:
            with lock:
                names[:] = msg.data.split('\n')
                lock.notify_all()

        detections: list[tuple[bytes, float]] = []
        det_sub = None
        if _vision_msgs():
            from vision_msgs.msg import Detection3DArray
            det_sub = node.create_subscription(Detection3DArray, fqn + '/detections',
                                     lambda raw: detections.append((raw, time.monotonic())),
                                     QoSProfile(depth=1000,
                                                reliability=ReliabilityPolicy.RELIABLE),
                                     raw=True)
        cls_sub = node.create_subscription(PointCloud2, fqn + '/classifications', on_answer,
                                           QoSProfile(depth=1000,
                                                      reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(String, fqn + '/class_names', on_names, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        while time.monotonic() < end and not (
                cls_sub.get_publisher_count() and names
                and (det_sub is None or det_sub.get_publisher_count())):
            time.sleep(0.05)
        if det_sub is not None:
            time.sleep(0.5)      # the node builds detections once it sees a subscriber
        log(f'node {fqn} found; sending {len(bag.messages)} message(s) at {rate:g} x the '
            'recorded rate')
        base, t0 = bag.messages[0].log_ns, time.monotonic()
        for m in bag.messages:
            delay = t0 + (m.log_ns - base) / 1e9 / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            with lock:
                waiting[(m.stamp_ns, m.frame_id)].append(m.index)
                sent_at[m.index] = time.monotonic()
            pubs[m.topic].publish(m.raw)
        with lock:
            while len(got) < len(sent_at):
                last = max([*sent_at.values(), *(t for _, t in got.values())])
                if time.monotonic() - last > timeout:
                    break
                lock.wait(0.2)
            answered = dict(got)
            class_names = list(names)
    finally:
        graph.close()
    answers: list[ObjectAnswer] = []
    for m in bag.messages:
        if m.index not in answered:
            continue
        msg, t = answered[m.index]
        d = decode_classifications(msg)
        answers += _rows(m, d['segment_id'].tolist(), d, class_names,
                         (t - sent_at[m.index]) * 1e3)
    info = {'node': fqn, 'sent': len(sent_at), 'answered': len(answered),
            'unmatched_answers': extra['unmatched'],
            # each answer at the bag time it would have had: recorded start + its delay
            'answer_messages': [(answered[i][0], base + int((answered[i][1] - t0) * 1e9))
                                for i in sorted(answered)],
            'detections': [(bytes(raw), base + int((t - t0) * 1e9)) for raw, t in detections]}
    return answers, class_names, info


def summarise(answers: list[ObjectAnswer], messages: int, answered: int) -> dict[str, Any]:
    """Objects per class, unknown share, latency percentiles (ms, live only)."""
    per_class = Counter(a.label for a in answers)
    lat = [a.latency_ms for a in answers if a.latency_ms is not None]
    pct = {f'p{q}': round(float(np.percentile(lat, q)), 2) for q in (50, 90, 99)} if lat else {}
    return {'messages': messages, 'messages_answered': answered, 'objects': len(answers),
            'objects_per_class': dict(sorted(per_class.items(), key=lambda kv: -kv[1])),
            'unknown_share': per_class.get('unknown', 0) / len(answers) if answers else 0.0,
            'latency_ms': pct}


def format_summary(summary: dict[str, Any]) -> str:
    lines = [f'{summary["objects"]} object(s) in {summary["messages_answered"]} of '
             f'{summary["messages"]} message(s); unknown {100 * summary["unknown_share"]:.1f} %']
    lines += [f'  {label}: {n}' for label, n in summary['objects_per_class'].items()]
    if summary['latency_ms']:
        lat = summary['latency_ms']
        lines.append(f'latency p50 / p90 / p99: {lat["p50"]} / {lat["p90"]} / {lat["p99"]} ms')
    return '\n'.join(lines)


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


CSV_COLUMNS = ('stamp_ns', 'topic', 'frame_id', 'segment', 'label', 'class_id', 'score',
               'topk', 'latency_ms', 'x', 'y', 'z')


def write_answers(answers: list[ObjectAnswer], header: dict[str, Any], *,
                  json_path: str | os.PathLike[str] | None = None,
                  csv_path: str | os.PathLike[str] | None = None) -> list[Path]:
    """JSON ({header..., 'answers': [...]}) and/or CSV (one row per object), atomically."""
    written = []
    if json_path:
        doc = dict(header, answers=[asdict(a) for a in answers])
        _atomic_write(Path(json_path), json.dumps(doc, indent=1) + '\n')
        written.append(Path(json_path))
    if csv_path:
        import io
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(CSV_COLUMNS)
        for a in answers:
            w.writerow([a.stamp_ns, a.topic, a.frame_id, a.segment, a.label, a.class_id,
                        f'{a.score:.6f}', ' '.join(f'{n}:{s:.4f}' for n, s in a.topk),
                        '' if a.latency_ms is None else f'{a.latency_ms:.3f}', *a.centroid])
        _atomic_write(Path(csv_path), buf.getvalue())
        written.append(Path(csv_path))
    return written


def _vision_msgs() -> bool:
    try:
        import vision_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


DETECTIONS = 'vision_msgs/msg/Detection3DArray'


def _with_vision_msgs(typestore: Any) -> bool:
    """Register vision_msgs' message definitions (from its ROS share) in `typestore`."""
    if DETECTIONS in typestore.types:
        return True
    try:
        from ament_index_python.packages import get_package_share_directory
        from rosbags.typesys import get_types_from_msg
        share = Path(get_package_share_directory('vision_msgs')) / 'msg'
        types: dict[str, Any] = {}
        for f in sorted(share.glob('*.msg')):
            types.update(get_types_from_msg(f.read_text(), f'vision_msgs/msg/{f.stem}'))
        typestore.register(types)
    except Exception:  # noqa: BLE001 - no vision_msgs share: the bag goes without detections
        return False
    return DETECTIONS in typestore.types


def write_output_bag(bag: BagClouds, out: str | os.PathLike[str],
                     answer_msgs: list[tuple[bytes, int]], answers_topic: str,
                     storage: str = 'mcap',
                     detections: list[tuple[bytes, int]] | None = None,
                     detections_topic: str = '') -> Path:
    """A new bag: the input clouds as recorded plus the answers (raw CDR, log time ns).

    The answers are sensor_msgs/PointCloud2 classifications on `answers_topic` and, when
    given (and vision_msgs' definitions are found), Detection3DArray on `detections_topic`.
    Nothing is left behind when writing fails.
    """
    import shutil

    from rosbags.rosbag2 import StoragePlugin, Writer

    out = Path(out)
    if out.exists():
        raise ReplayError(f'{out}: already exists; remove it or choose another path')
    typestore = _typestore()
    writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP if storage == 'mcap'
                    else StoragePlugin.SQLITE3)
    try:
        writer.open()
        conns = {t: writer.add_connection(t, POINTCLOUD2, typestore=typestore)
                 for t in bag.topics}
        ans = writer.add_connection(answers_topic, POINTCLOUD2, typestore=typestore)
        rows = [(m.log_ns, conns[m.topic], m.raw) for m in bag.messages]
        rows += [(t, ans, raw) for raw, t in answer_msgs]
        if detections and _with_vision_msgs(typestore):
            det = writer.add_connection(detections_topic, DETECTIONS, typestore=typestore)
            rows += [(t, det, raw) for raw, t in detections]
        for log_ns, conn, raw in sorted(rows, key=lambda r: r[0]):
            writer.write(conn, log_ns, raw)
        writer.close()
    except BaseException:
        writer.abort()
        shutil.rmtree(out, ignore_errors=True)
        raise
    return out
