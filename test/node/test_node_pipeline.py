"""Classifier node end to end.

Real rclpy + Fast DDS, the node in its own process, real ModelNet40 test clouds in sensor
frames on two input topics.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import re

import numpy as np
import pytest

from node_testing import (BANK_CLASSES, NODE_FQN, REPO, TEST_NUM_POINTS, Harness, NodeProcess,
                          assert_same_labels, cloud_msg, harness, latched_qos, latest_diagnostics,
                          pick, stamp, stamp_key, tiny_bank, to_sensor_frame)

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

TOPICS = ('objects_front', 'objects_rear')
FRAMES = ('lidar_front', 'lidar_rear')
ANSWER_TIMEOUT_S = 60.0


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': list(TOPICS), 'queue_size': 16, 'max_batch': 8,
                        'qos_depth': 20},
                       tmp_path_factory.mktemp('node') / 'node.log',
                       params_file=REPO / 'config' / 'classifier.yaml')
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope='module')
def io(harness: Harness, node: NodeProcess) -> dict:
    """Publishers on both input topics and collectors of every output, node ready."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from node_testing import reliable_qos

    pubs = [harness.node.create_publisher(PointCloud2, t, reliable_qos(20)) for t in TOPICS]
    out = {
        'pubs': pubs,
        'cls': harness.collect(PointCloud2, f'{NODE_FQN}/classifications', reliable_qos(100)),
        'markers': harness.collect(MarkerArray, f'{NODE_FQN}/markers', reliable_qos(100)),
        'diag': harness.collect(DiagnosticArray, '/diagnostics', reliable_qos(50)),
    }
    harness.wait_for_subscribers(pubs, node)
    harness.spin_for(0.5)  # let the output side match too
    return out


def _answers(io: dict, key: tuple[int, int]) -> list:
    return [m for m in io['cls'] if stamp_key(m.header) == key]


def test_two_topics_every_message_answered_with_offline_labels(
        harness: Harness, node: NodeProcess, io: dict, tiny_bank: Path) -> None:
    from point_gn_ros.pointcloud2 import decode_classifications

    rng = np.random.default_rng(1)
    xyz, _ = pick('test', BANK_CLASSES, 2)
    clouds = [to_sensor_frame(c, rng) for c in xyz]
    sent = []  # (topic index, stamp key, cloud)
    for i, cloud in enumerate(clouds):
        t = i % 2
        key = (1000 + i, 500 * i)
        io['pubs'][t].publish(cloud_msg(cloud, FRAMES[t], stamp(*key)))
        sent.append((t, key, cloud))
        if t == 1:  # a pair at a time: no queue ever overflows, so every message is answered
            assert harness.spin_until(lambda k=key: _answers(io, k), ANSWER_TIMEOUT_S), node.log()
    assert harness.spin_until(lambda: all(_answers(io, k) for _, k, _ in sent), ANSWER_TIMEOUT_S)

    labels = []
    for t, key, cloud in sent:
        answers = _answers(io, key)
        assert len(answers) == 1, f'message {key} answered {len(answers)} times'
        msg = answers[0]
        assert msg.header.frame_id == FRAMES[t]
        res = decode_classifications(msg)
        assert len(res['class_id']) == 1
        labels.append(int(res['class_id'][0]))
        assert res['topic_index'][0] == t and res['segment_id'][0] == -1
        assert res['topk_ids'].shape == (1, 5) and res['topk_ids'][0, 0] == labels[-1]
        assert 0.0 <= res['score'][0] <= 1.0
        np.testing.assert_allclose(res['centroid'][0], cloud.mean(axis=0), atol=1e-4)
    assert_same_labels(labels, tiny_bank, clouds)

    # Markers: same header, "label score" text above a box around the object.
    harness.spin_for(0.3)
    for t, key, cloud in sent:
        arrays = [m for m in io['markers'] if m.markers and stamp_key(m.markers[0].header) == key]
        assert len(arrays) == 1
        texts = [m for m in arrays[0].markers if m.type == m.TEXT_VIEW_FACING]
        boxes = [m for m in arrays[0].markers if m.type == m.LINE_LIST]
        assert len(texts) == 1 and len(boxes) == 1
        assert texts[0].header.frame_id == FRAMES[t]
        assert re.fullmatch(r'\w+ \d\.\d\d', texts[0].text)
        assert texts[0].text.split()[0] in BANK_CLASSES
        assert texts[0].pose.position.z > cloud[:, 2].max()
        pts = np.array([(p.x, p.y, p.z) for p in boxes[0].points])
        np.testing.assert_allclose(pts.min(axis=0), cloud.min(axis=0), atol=1e-4)
        np.testing.assert_allclose(pts.max(axis=0), cloud.max(axis=0), atol=1e-4)


def test_class_names_latched(harness: Harness, io: dict) -> None:
    from std_msgs.msg import String

    names = harness.collect(String, f'{NODE_FQN}/class_names', latched_qos())
    assert harness.spin_until(lambda: names, 15.0)
    assert names[0].data.split('\n') == list(BANK_CLASSES)


def _malformed(good) -> list:  # noqa: ANN001 - a sensor_msgs/PointCloud2
    """One message per kind of malformation, each a copy of `good` with one thing broken."""
    import copy

    from sensor_msgs.msg import PointField

    def variant(**changes) -> object:  # noqa: ANN003
        m = copy.deepcopy(good)
        for k, v in changes.items():
            setattr(m, k, v)
        return m

    no_z = variant(fields=[f for f in good.fields if f.name != 'z'])
    bad_type = variant(fields=[PointField(name=f.name, offset=f.offset, datatype=99, count=1)
                               if f.name == 'y' else f for f in good.fields])
    off_end = variant(fields=[PointField(name=f.name, offset=good.point_step, datatype=7, count=1)
                              if f.name == 'z' else f for f in good.fields])
    truncated = variant(data=bytes(good.data)[:-7])
    short_row = variant(row_step=good.point_step * good.width - 1)
    return [no_z, bad_type, off_end, truncated, short_row]


def test_malformed_input_counted_warned_and_survived(harness: Harness, node: NodeProcess,
                                                     io: dict) -> None:
    rng = np.random.default_rng(2)
    cloud = to_sensor_frame(pick('test', ('chair',), 1)[0][0], rng)
    good = cloud_msg(cloud, FRAMES[0], stamp(2000))
    malformed = _malformed(good)
    with_nans = cloud.copy()
    with_nans[::3] = np.nan
    all_nan = np.full((50, 3), np.nan, np.float32)
    few = cloud[:5]
    too_few = [cloud_msg(all_nan, FRAMES[0], stamp(2001)), cloud_msg(few, FRAMES[0], stamp(2002)),
               cloud_msg(np.zeros((0, 3), np.float32), FRAMES[0], stamp(2003))]
    for msg in malformed + too_few:
        io['pubs'][0].publish(msg)
        harness.spin_for(0.02)
    nan_key, last_key = (2004, 0), (2005, 0)
    io['pubs'][0].publish(cloud_msg(with_nans, FRAMES[0], stamp(*nan_key)))
    io['pubs'][1].publish(cloud_msg(cloud, FRAMES[1], stamp(*last_key)))
    assert harness.spin_until(lambda: _answers(io, nan_key) and _answers(io, last_key),
                              ANSWER_TIMEOUT_S), node.log()
    assert node.proc.poll() is None

    from point_gn_ros.pointcloud2 import decode_classifications
    finite = with_nans[np.isfinite(with_nans).all(axis=1)]
    res = decode_classifications(_answers(io, nan_key)[0])
    np.testing.assert_allclose(res['centroid'][0], finite.mean(axis=0), atol=1e-4)
    for k in (2000, 2001, 2002, 2003):
        assert not _answers(io, (k, 0))

    # Diagnostics count every rejection by reason.
    def counted() -> bool:
        d = latest_diagnostics(io['diag'])
        return int(d.get('rejected', 0)) >= len(malformed) + len(too_few)
    assert harness.spin_until(counted, 5.0), latest_diagnostics(io['diag'])
    d = latest_diagnostics(io['diag'])
    reasons = {k: int(v) for k, v in d.items() if k.startswith('rejected.')}
    assert reasons.pop('rejected.too few points') == len(too_few)
    assert sum(reasons.values()) == len(malformed)
    assert len(reasons) >= 4, reasons   # distinct reasons, not one lump

    # Warnings name the topic and the reason, at most one per topic per period.
    warnings = [ln for ln in node.log().splitlines()
                if 'dropped a message on /objects_front' in ln]
    assert warnings and 'missing field' in warnings[0]
    assert len(warnings) <= 2


def test_huge_finite_coordinates_are_classified_not_lost(harness: Harness, node: NodeProcess,
                                                         io: dict) -> None:
    # Finite float32 coordinates near the type's limit overflow if centred in float32;
    # normalisation runs in float64, so such a cloud is an ordinary object.
    huge = np.full((40, 3), 3.4e38, np.float32)
    huge[::3] = -3.4e38
    rng = np.random.default_rng(5)
    good = to_sensor_frame(pick('test', ('lamp',), 1)[0][0], rng)
    huge_key, good_key = (5000, 0), (5001, 0)
    io['pubs'][0].publish(cloud_msg(huge, FRAMES[0], stamp(*huge_key)))
    io['pubs'][1].publish(cloud_msg(good, FRAMES[1], stamp(*good_key)))
    assert harness.spin_until(lambda: _answers(io, good_key) and _answers(io, huge_key),
                              ANSWER_TIMEOUT_S), node.log()
    assert node.proc.poll() is None
    assert 'failed to classify' not in node.log()


def test_diagnostics(harness: Harness, io: dict) -> None:
    # Diagnostics come at 1 Hz: wait for the one that has counted every answer so far.
    assert harness.spin_until(lambda: len(io['diag']) >= 2 and int(
        latest_diagnostics(io['diag']).get('processed', 0)) >= 15, 5.0)
    d = latest_diagnostics(io['diag'])
    for key in ('input_rate_hz', 'processed_rate_hz', 'latency_receipt_p50_ms',
                'latency_receipt_p99_ms', 'latency_stamp_p50_ms', 'latency_stamp_p99_ms',
                'queue_depth', 'dropped', 'rejected'):
        assert key in d, key
    assert int(d['processed']) >= 15 and int(d['dropped']) == 0
    assert 0.0 < float(d['latency_receipt_p50_ms']) <= float(d['latency_receipt_p99_ms'])
    bank = latest_diagnostics(io['diag'], ': bank')
    assert bank['entries'] == '18' and bank['classes'] == '6'
    topic = latest_diagnostics(io['diag'], f': input /{TOPICS[1]}')
    assert topic['topic_index'] == '1' and int(topic['processed']) >= 7


def test_parameters_are_described_and_read_only_unless_live(harness: Harness, io: dict) -> None:
    from rcl_interfaces.srv import DescribeParameters, GetParameters

    from point_gn_ros.node.params import LIVE, PARAMETERS

    def call(srv_type, name: str, request):  # noqa: ANN001, ANN202
        client = harness.node.create_client(srv_type, f'{NODE_FQN}/{name}')
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(request)
        assert harness.spin_until(future.done, 10.0)
        return future.result()

    names = [*PARAMETERS, 'class_names']
    described = call(DescribeParameters, 'describe_parameters',
                     DescribeParameters.Request(names=names)).descriptors
    by_name = {d.name: d for d in described}
    assert set(by_name) == set(names)
    assert all(d.description for d in described)
    # allow_parameter_changes is false here (config/classifier.yaml): no peer may change
    # a live parameter either (test_node_ros starts a node with it true: LIVE writable)
    assert {d.name for d in described if not d.read_only} == {'class_names'}
    assert LIVE <= set(by_name)
    assert by_name['top_k'].integer_range[0].from_value == 1
    assert by_name['unknown_threshold'].floating_point_range
    values = call(GetParameters, 'get_parameters', GetParameters.Request(
        names=['class_names', 'num_points', 'input_topics'])).values
    assert list(values[0].string_array_value) == list(BANK_CLASSES)
    assert values[1].integer_value == TEST_NUM_POINTS
    assert list(values[2].string_array_value) == list(TOPICS)


def test_sigint_exits_cleanly(node: NodeProcess) -> None:
    assert node.proc.poll() is None
    assert node.stop() == 0
    log = node.log()
    assert 'Traceback' not in log, log
    assert 'worker stopped' in log, log
