"""The node fits the graph it joins, over real DDS: any publisher's QoS, PCL-style label fields.

One node process at the default QoS ('auto') with five input topics:

* `sensor_objects`: a `qos_profile_sensor_data` (best-effort) publisher that appears after
  the node subscribed reliable: the node follows it and answers;
* `reliable_objects`: a reliable publisher, answered as before;
* `forced_reliable` (`topics.forced_reliable.qos_reliability: reliable`) with a best-effort
  publisher: counted, warned once with both policies, WARN in /diagnostics, never "no
  publisher";
* `labelled`: the node's `segment_field: label`, ids 0xFFFFFFFF (uint32) and 65535 (uint16)
  being unsegmented points, not an object nor a dropped message;
* the single-object topics carry no `label` field: `topics.<key>.segment_field: ''` serves
  them.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
import time

import numpy as np
import pytest

from node_testing import (TEST_NUM_POINTS, Harness, NodeProcess, cloud_msg, harness,
                          latest_diagnostics, pick, reliable_qos, sensor_qos, stamp,
                          stamp_key, tiny_bank, to_sensor_frame)

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

NODE_FQN = '/qos_test_classifier'
SENSOR, RELIABLE, FORCED, LABELLED = ('sensor_objects', 'reliable_objects', 'forced_reliable',
                                      'labelled')
ANSWER_TIMEOUT_S = 60.0
RESEND_S = 5.0             # an unanswered cloud is published again after this long


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': [SENSOR, RELIABLE, FORCED, LABELLED],
                        'segment_field': 'label', 'input_timeout_s': 2.0,
                        f'topics.{SENSOR}.segment_field': '',
                        f'topics.{RELIABLE}.segment_field': '',
                        f'topics.{FORCED}.segment_field': '',
                        f'topics.{FORCED}.qos_reliability': 'reliable'},
                       tmp_path_factory.mktemp('node') / 'node.log', node_name=NODE_FQN[1:])
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope='module')
def io(harness: Harness, node: NodeProcess) -> dict:
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    out = {'reliable': harness.node.create_publisher(PointCloud2, RELIABLE, reliable_qos()),
           'labelled': harness.node.create_publisher(PointCloud2, LABELLED, reliable_qos()),
           'cls': harness.collect(PointCloud2, f'{NODE_FQN}/classifications',
                                  reliable_qos(200)),
           'diag': harness.collect(DiagnosticArray, '/diagnostics', reliable_qos(50))}
    harness.wait_for_subscribers([out['reliable'], out['labelled']], node)
    return out


def _objects(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    xyz, _ = pick('test', ('chair', 'airplane'), (n + 1) // 2)
    return [to_sensor_frame(c, rng) for c in xyz[:n]]


def _answer(io: dict, key: tuple[int, int]) -> dict | None:
    from point_gn_ros.pointcloud2 import decode_classifications
    for msg in io['cls']:
        if stamp_key(msg.header) == key:
            return decode_classifications(msg)
    return None


def _publish_all(harness: Harness, io: dict, pub: object, clouds: list[np.ndarray],
                 sec: int, node: NodeProcess) -> list[dict]:
    """Each cloud published until answered (every RESEND_S seconds, ANSWER_TIMEOUT_S in all).

    A best-effort subscription drops what arrives before its side of a new publisher's match
    is complete (`wait_for_subscribers` sees only the publisher's side), so an unanswered
    cloud is sent again; the answers are looked up by stamp.
    """
    keys = [(sec, i) for i in range(len(clouds))]
    end = time.monotonic() + ANSWER_TIMEOUT_S
    while time.monotonic() < end:
        for key, cloud in zip(keys, clouds, strict=True):
            if _answer(io, key) is None:
                pub.publish(cloud_msg(cloud, 'velodyne', stamp(*key)))
                harness.spin_for(0.05)
        if harness.spin_until(lambda: all(_answer(io, k) for k in keys), RESEND_S):
            return [_answer(io, k) for k in keys]
    raise AssertionError(node.log())


def test_sensor_data_and_reliable_publishers_are_both_answered(
        harness: Harness, node: NodeProcess, io: dict) -> None:
    from sensor_msgs.msg import PointCloud2

    clouds = _objects(6, 1)
    answers = _publish_all(harness, io, io['reliable'], clouds, 100, node)
    assert {int(a['topic_index'][0]) for a in answers} == {1}
    # A sensor-data publisher joins after the node subscribed (reliable, nobody there yet):
    # the node re-subscribes best effort and hears it.
    sensor = harness.node.create_publisher(PointCloud2, SENSOR, sensor_qos())
    harness.wait_for_subscribers([sensor], node, timeout=30.0)
    answers = _publish_all(harness, io, sensor, clouds, 200, node)
    assert [a['segment_id'].tolist() for a in answers] == [[-1]] * len(clouds)
    assert {int(a['topic_index'][0]) for a in answers} == {0}
    assert f'input /{SENSOR}: publishers changed, subscribed again with best_effort' \
        in node.log()
    assert harness.spin_until(
        lambda: latest_diagnostics(io['diag'], f'input /{SENSOR}').get('qos_reliability')
        == 'best_effort', 5.0)
    # Both kinds on one topic: the best-effort subscription hears the reliable one too.
    both = harness.node.create_publisher(PointCloud2, SENSOR, reliable_qos())
    harness.wait_for_subscribers([both], node, timeout=30.0)
    answers = _publish_all(harness, io, both, clouds[:3], 250, node)
    assert {int(a['topic_index'][0]) for a in answers} == {0}
    assert node.log().count(f'input /{SENSOR}: publishers changed') == 1


def test_incompatible_publisher_is_described_not_missing(
        harness: Harness, node: NodeProcess, io: dict) -> None:
    from sensor_msgs.msg import PointCloud2

    pub = harness.node.create_publisher(PointCloud2, FORCED, sensor_qos())
    for i in range(3):
        pub.publish(cloud_msg(_objects(1, 2)[0], 'velodyne', stamp(300, i)))
        harness.spin_for(0.2)

    def described() -> bool:
        d = latest_diagnostics(io['diag'], f'input /{FORCED}')
        return ('publisher best_effort, subscription reliable' in d.get('_message', '')
                and int(d.get('incompatible_qos_events', 0)) >= 1)
    assert harness.spin_until(described, 20.0), (latest_diagnostics(io['diag'],
                                                                    f'input /{FORCED}'),
                                                 node.log())
    # Well past input_timeout_s: still described as incompatible, never "no publisher".
    harness.spin_for(3.0)
    d = latest_diagnostics(io['diag'], f'input /{FORCED}')
    assert d['_level'] == '1' and 'no publisher' not in d['_message'], d
    assert d['qos_reliability'] == 'reliable' and d['incompatible_publishers'] == '1'
    pipe = latest_diagnostics(io['diag'])
    assert int(pipe['incompatible_qos_events']) >= 1 and 'no publisher' not in pipe['_message']
    assert all(_answer(io, (300, i)) is None for i in range(3))
    line = (f'input /{FORCED}: a publisher offers incompatible QoS (publisher best_effort, '
            'subscription reliable)')
    assert node.log().count(line) == 1, node.log()


@pytest.mark.parametrize('dtype', [np.uint32, np.uint16])
def test_unsigned_no_label_ids_are_unsegmented(harness: Harness, node: NodeProcess, io: dict,
                                               dtype: type) -> None:
    """PCL's uint32 0xFFFFFFFF (and uint16 65535): neither a dropped message nor an object."""
    a, b = _objects(2, 3)
    rng = np.random.default_rng(4)
    clutter = rng.uniform(-10, 10, (400, 3)).astype(np.float32)     # 20 x 20 m of "no label"
    xyz = np.concatenate([a, b, clutter])
    none = np.iinfo(dtype).max
    label = np.concatenate([np.full(len(a), 7), np.full(len(b), 9),
                            np.full(len(clutter), none)]).astype(dtype)
    key = (400, int(np.dtype(dtype).itemsize))
    io['labelled'].publish(cloud_msg(xyz, 'velodyne', stamp(*key), {'label': label}))
    assert harness.spin_until(lambda: _answer(io, key) is not None, ANSWER_TIMEOUT_S), \
        node.log()
    assert _answer(io, key)['segment_id'].tolist() == [7, 9]
    pipe = latest_diagnostics(io['diag'])
    assert int(pipe.get('rejected', 0)) == 0, pipe


def test_misspelt_runtime_parameter_names_the_closest(harness: Harness, node: NodeProcess,
                                                      io: dict) -> None:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    req = SetParameters.Request(parameters=[
        Parameter('unkown_threshold', value=0.5).to_parameter_msg()])
    result = harness.call(SetParameters, f'{NODE_FQN}/set_parameters', req,
                          resend_s=5.0).results[0]
    assert not result.successful
    assert "'unkown_threshold' (did you mean 'unknown_threshold'?)" in result.reason, \
        result.reason
