"""Classifier node with a segment field.

Multi-object clouds, marker clean-up, and overload (bounded queues that drop the oldest and
answer the freshest).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from node_testing import (BANK_CLASSES, NODE_FQN, TEST_NUM_POINTS, Harness, NodeProcess,
                          assert_same_labels, cloud_msg, harness, latest_diagnostics, pick,
                          reliable_qos, stamp, stamp_key, tiny_bank, to_sensor_frame)

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

TOPIC = 'segmented_objects'
QUEUE_SIZE = 2
ANSWER_TIMEOUT_S = 60.0


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': [TOPIC], 'segment_field': 'segment', 'min_points': 16,
                        'queue_size': QUEUE_SIZE, 'max_batch': 4,
                        'qos_reliability': 'reliable', 'qos_depth': 50},
                       tmp_path_factory.mktemp('node') / 'node.log')
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope='module')
def io(harness: Harness, node: NodeProcess) -> dict:
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    pub = harness.node.create_publisher(PointCloud2, TOPIC, reliable_qos(100))
    out = {
        'pub': pub,
        'cls': harness.collect(PointCloud2, f'{NODE_FQN}/classifications', reliable_qos(200)),
        'markers': harness.collect(MarkerArray, f'{NODE_FQN}/markers', reliable_qos(200)),
        'diag': harness.collect(DiagnosticArray, '/diagnostics', reliable_qos(50)),
    }
    harness.wait_for_subscribers([pub], node)
    harness.spin_for(0.5)
    return out


def _scene(objects: list[np.ndarray], seg_ids: list[int], rng: np.random.Generator
           ) -> tuple[np.ndarray, np.ndarray]:
    """Objects side by side plus a 5-point segment and unsegmented (-1) clutter, shuffled."""
    parts = [o + np.array([0.0, 2.0 * i, 0.0], np.float32) for i, o in enumerate(objects)]
    ids = [np.full(len(o), s, np.int32) for o, s in zip(objects, seg_ids, strict=True)]
    parts.append(rng.normal(0, 0.05, (5, 3)).astype(np.float32) + np.float32(9.0))
    ids.append(np.full(5, 99, np.int32))
    parts.append(rng.uniform(-5, 5, (200, 3)).astype(np.float32))
    ids.append(np.full(200, -1, np.int32))
    xyz, seg = np.concatenate(parts), np.concatenate(ids)
    order = rng.permutation(len(xyz))
    return xyz[order], seg[order]


def _answers(io: dict, key: tuple[int, int]) -> list:
    return [m for m in io['cls'] if stamp_key(m.header) == key]


def test_multi_object_clouds(harness: Harness, node: NodeProcess, io: dict,
                             tiny_bank: Path) -> None:
    from point_gn_ros.pointcloud2 import decode_classifications

    rng = np.random.default_rng(3)
    xyz, _ = pick('test', BANK_CLASSES[:3], 1, offset=5)
    objects = [to_sensor_frame(c, rng) for c in xyz]
    seg_ids = [3, 7, 11]
    scene, seg = _scene(objects, seg_ids, rng)
    key = (3000, 1)
    io['pub'].publish(cloud_msg(scene, 'camera', stamp(*key), {'segment': seg}))
    assert harness.spin_until(lambda: _answers(io, key), ANSWER_TIMEOUT_S), node.log()

    res = decode_classifications(_answers(io, key)[0])
    assert list(res['segment_id']) == seg_ids           # the 5-point segment and -1 skipped
    # The node sees each object as the points carrying its id, in scene order.
    clouds = [scene[seg == s] for s in seg_ids]
    assert_same_labels(list(res['class_id']), tiny_bank, clouds)
    np.testing.assert_allclose(res['centroid'], [c.mean(axis=0) for c in clouds], atol=1e-4)
    assert set(res['topic_index']) == {0}

    # Next message with one object: markers of ids 1 and 2 are deleted, in both namespaces.
    key2 = (3001, 0)
    single, seg1 = _scene(objects[:1], [5], rng)
    io['pub'].publish(cloud_msg(single, 'camera', stamp(*key2), {'segment': seg1}))
    assert harness.spin_until(lambda: _answers(io, key2), ANSWER_TIMEOUT_S)
    harness.spin_for(0.3)
    first, second = (next(a for a in io['markers'] if a.markers
                          and stamp_key(a.markers[0].header) == k) for k in (key, key2))
    assert sum(m.action == m.ADD for m in first.markers) == 6
    adds = [(m.ns, m.id) for m in second.markers if m.action == m.ADD]
    deletes = sorted((m.ns, m.id) for m in second.markers if m.action == m.DELETE)
    assert sorted(adds) == [(f'{TOPIC}/boxes', 0), (f'{TOPIC}/labels', 0)]
    assert deletes == sorted((f'{TOPIC}/{ns}', i) for ns in ('boxes', 'labels') for i in (1, 2))

    d = latest_diagnostics(io['diag'])
    harness.spin_until(lambda: int(latest_diagnostics(io['diag']).get('skipped_segments', 0))
                       >= 2, 3.0)
    d = latest_diagnostics(io['diag'])
    assert int(d['skipped_segments']) >= 2


def test_overload_drops_oldest_and_answers_freshest(harness: Harness, node: NodeProcess,
                                                     io: dict) -> None:
    rng = np.random.default_rng(4)
    xyz, _ = pick('test', BANK_CLASSES, 1)
    clouds = [to_sensor_frame(c, rng) for c in xyz]
    n = 60
    keys = [(4000 + i, 0) for i in range(n)]
    for i, key in enumerate(keys):  # as fast as we can: far faster than the node classifies
        cloud = clouds[i % len(clouds)]
        io['pub'].publish(cloud_msg(cloud, 'camera', stamp(*key),
                                    {'segment': np.zeros(len(cloud), np.int32)}))
    assert harness.spin_until(lambda: _answers(io, keys[-1]), ANSWER_TIMEOUT_S), node.log()
    harness.spin_for(1.5)   # anything still queued comes out now

    answered = [k for k in keys if _answers(io, k)]
    assert keys[-1] in answered                 # the freshest message is always answered
    assert len(answered) < n                    # ... and not the whole backlog
    # Answers come in order: drops only ever remove older messages.
    order = [stamp_key(m.header) for m in io['cls'] if stamp_key(m.header) in set(keys)]
    assert order == sorted(order)

    # Every message the node received was either answered or dropped from its queue (a
    # reliable KEEP_LAST reader may also lose some before the node sees them, on a busy CPU).
    def settled() -> bool:
        d = latest_diagnostics(io['diag'])
        return bool(d) and int(d['queue_depth']) == 0 and int(d['processed']) == len(io['cls'])
    assert harness.spin_until(settled, 5.0), latest_diagnostics(io['diag'])
    d = latest_diagnostics(io['diag'])
    assert int(d['dropped']) > 0
    assert int(d['received']) == int(d['processed']) + int(d['dropped'])
    assert int(d['rejected']) == 0
    capacity = int(d['queue_capacity'])
    assert capacity == QUEUE_SIZE
    depths = [int(latest_diagnostics([a]).get('queue_depth', 0)) for a in io['diag']]
    assert max(depths) <= capacity
    levels = [latest_diagnostics([a]).get('_level') for a in io['diag']]
    assert str(1) in levels                     # WARN while dropping


def test_sigterm_exits_cleanly(node: NodeProcess) -> None:
    import signal
    assert node.stop(signal.SIGTERM) == 0
    assert 'Traceback' not in node.log()
