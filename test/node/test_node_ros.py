"""The node as a ROS user drives it: lifecycle, vision_msgs outputs, live parameters, frames, QoS.

One managed node process with autostart:=false, driven from this process through its
lifecycle and parameter services (what `ros2 lifecycle set` / `ros2 param set` call).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from conftest import load_modelnet_split
import numpy as np
import pytest

from node_testing import (BANK_CLASSES, REPO, TEST_NUM_POINTS, Harness, NodeProcess, cloud_msg,
                          harness, latched_qos, latest_diagnostics, pick, reliable_qos,
                          require_ros_extras, stamp, stamp_key, tiny_bank, to_sensor_frame)

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

TOPIC, SILENT = 'objects', 'nobody_publishes_here'
OPTICAL = 'camera_depth_optical_frame'
# A remapped node name, with the shipped `/**` YAML: the parameters still apply.
NODE_FQN = '/lifecycle_test_classifier'
ANSWER_TIMEOUT_S = 60.0
INPUT_TIMEOUT_S = 2.0


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    # Default QoS (reliable), a misspelt parameter, and a topic nobody publishes on.
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': [TOPIC, SILENT], 'autostart': False,
                        'queue_size': 64, 'qos_depth': 64, 'input_timeout_s': INPUT_TIMEOUT_S,
                        'unkown_threshold': 0.5, 'allow_parameter_changes': True},
                       tmp_path_factory.mktemp('node') / 'node.log',
                       params_file=REPO / 'config' / 'classifier.yaml', node_name=NODE_FQN[1:])
    try:
        yield proc
    finally:
        proc.stop()


# The state each transition ends in when it succeeds.
_GOAL = {'configure': 'inactive', 'activate': 'active', 'deactivate': 'inactive',
         'cleanup': 'unconfigured'}


def _lifecycle(harness: Harness, label: str) -> bool:
    """Trigger a transition; True when it succeeded.

    A transition is not idempotent, so it is not resent (Harness.call): when its response is
    lost, the node's state tells whether it took place, and only if not is it tried again.
    """
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState

    req = ChangeState.Request(transition=Transition(label=label))
    for attempt in range(2):
        try:
            return harness.call(ChangeState, f'{NODE_FQN}/change_state', req, 45.0).success
        except AssertionError:
            if attempt or _state(harness) == _GOAL[label]:
                return _state(harness) == _GOAL[label]
    return False


def _state(harness: Harness) -> str:
    from lifecycle_msgs.srv import GetState
    return harness.call(GetState, f'{NODE_FQN}/get_state', GetState.Request(),
                        resend_s=5.0).current_state.label


@pytest.fixture(scope='module')
def io(harness: Harness, node: NodeProcess) -> dict:
    """Node configured and activated from here; publishers and collectors of every output."""
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.node.outputs import vision_msgs_available

    pub = harness.node.create_publisher(PointCloud2, TOPIC, reliable_qos(64))
    out = {
        'pub': pub,
        'cls': harness.collect(PointCloud2, f'{NODE_FQN}/classifications', reliable_qos(200)),
        'diag': harness.collect(DiagnosticArray, '/diagnostics', reliable_qos(50)),
        'det': [],
        'vision': vision_msgs_available(),
    }
    if out['vision']:   # else the tests that need it skip (or fail in CI)
        from vision_msgs.msg import Detection3DArray
        out['det'] = harness.collect(Detection3DArray, f'{NODE_FQN}/detections',
                                     reliable_qos(200))
    assert _state(harness) == 'unconfigured', node.log()
    assert pub.get_subscription_count() == 0         # nothing subscribes before activate
    assert _lifecycle(harness, 'configure'), node.log()
    assert _state(harness) == 'inactive'
    assert _lifecycle(harness, 'activate'), node.log()
    harness.wait_for_subscribers([pub], node)
    harness.spin_for(0.5)
    return out


def _answers(io: dict, key: tuple[int, int], what: str = 'cls') -> list:
    return [m for m in io[what] if stamp_key(m.header) == key]


def _send(harness: Harness, io: dict, cloud: np.ndarray, key: tuple[int, int],
          frame: str = 'base_link', wait: bool = True) -> None:
    io['pub'].publish(cloud_msg(cloud, frame, stamp(*key)))
    if wait:
        assert harness.spin_until(lambda: _answers(io, key), ANSWER_TIMEOUT_S)


def test_unknown_parameter_warns_with_the_closest_name(io: dict, node: NodeProcess) -> None:
    assert "unknown parameter 'unkown_threshold' ignored; did you mean 'unknown_threshold'?" \
        in node.log()


def test_detections_and_label_info(harness: Harness, node: NodeProcess, io: dict) -> None:
    require_ros_extras('vision_msgs.msg')
    from point_gn_ros.pointcloud2 import decode_classifications
    from vision_msgs.msg import LabelInfo

    labels = harness.collect(LabelInfo, f'{NODE_FQN}/label_info', latched_qos())
    assert harness.spin_until(lambda: labels, 15.0)           # transient local: late joiner
    assert [(c.class_id, c.class_name) for c in labels[0].class_map] == list(
        enumerate(BANK_CLASSES))

    rng = np.random.default_rng(11)
    cloud = to_sensor_frame(pick('test', ('guitar',), 1)[0][0], rng)
    key = (7000, 7)
    _send(harness, io, cloud, key, frame='lidar')
    assert harness.spin_until(lambda: _answers(io, key, 'det'), 10.0), node.log()
    arr = _answers(io, key, 'det')[0]
    assert arr.header.frame_id == 'lidar' and len(arr.detections) == 1
    det = arr.detections[0]
    assert det.id == '-1' and det.header.frame_id == 'lidar'
    box = det.bbox
    centre = np.array([box.center.position.x, box.center.position.y, box.center.position.z])
    size = np.array([box.size.x, box.size.y, box.size.z])
    np.testing.assert_allclose(centre - size / 2, cloud.min(axis=0), atol=1e-4)
    np.testing.assert_allclose(centre + size / 2, cloud.max(axis=0), atol=1e-4)
    names = [r.hypothesis.class_id for r in det.results]
    scores = [r.hypothesis.score for r in det.results]
    assert len(names) == 5 and set(names) <= set(BANK_CLASSES)
    assert scores == sorted(scores, reverse=True) and 0.0 <= scores[0] <= 1.0
    res = decode_classifications(_answers(io, key)[0])            # same answer, both outputs
    assert names[0] == BANK_CLASSES[int(res['class_id'][0])]
    assert scores[0] == pytest.approx(float(res['score'][0]), abs=1e-6)
    pos = det.results[0].pose.pose.position
    np.testing.assert_allclose([pos.x, pos.y, pos.z], cloud.mean(axis=0), atol=1e-4)


def test_live_parameters_take_effect_or_are_refused(harness: Harness, node: NodeProcess,
                                                    io: dict) -> None:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    def set_param(name: str, value: object) -> object:
        req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return harness.call(SetParameters, f'{NODE_FQN}/set_parameters', req,
                            resend_s=5.0).results[0]   # a set is idempotent

    assert set_param('top_k', 3).successful
    rng = np.random.default_rng(12)
    cloud = to_sensor_frame(pick('test', ('chair',), 1)[0][0], rng)
    key = (7100, 0)
    _send(harness, io, cloud, key)
    if io['vision']:
        assert harness.spin_until(lambda: _answers(io, key, 'det'), 10.0)
        assert len(_answers(io, key, 'det')[0].detections[0].results) == 3
    from point_gn_ros.pointcloud2 import decode_classifications
    assert decode_classifications(_answers(io, key)[0])['topk_ids'].shape == (1, 3)

    refused = set_param('num_points', 512)                   # shapes the bank: read-only
    assert not refused.successful and refused.reason
    refused = set_param('top_k', 0)                          # out of its range
    assert not refused.successful and refused.reason
    refused = set_param('unknown_threshold', 'high')         # wrong type
    assert not refused.successful
    assert set_param('top_k', 5).successful
    assert node.proc.poll() is None


def test_deactivate_stops_answers_and_activate_resumes(harness: Harness, node: NodeProcess,
                                                       io: dict) -> None:
    rng = np.random.default_rng(13)
    cloud = to_sensor_frame(pick('test', ('lamp',), 1)[0][0], rng)
    assert _lifecycle(harness, 'deactivate')
    assert _state(harness) == 'inactive'
    assert harness.spin_until(lambda: io['pub'].get_subscription_count() == 0, 10.0)
    key = (7200, 0)
    _send(harness, io, cloud, key, wait=False)
    harness.spin_for(3.0)
    assert not _answers(io, key) and not _answers(io, key, 'det')
    assert _lifecycle(harness, 'activate')
    harness.wait_for_subscribers([io['pub']], node)
    harness.spin_for(0.5)
    key = (7201, 0)
    _send(harness, io, cloud, key)


def test_optical_frame_scores_like_z_up(harness: Harness, node: NodeProcess, io: dict) -> None:
    """Held-out objects in a camera optical frame (REP 103) are labelled as in a z-up frame."""
    from point_gn_ros.pointcloud2 import decode_classifications

    xyz, truth = pick('test', BANK_CLASSES, 8, offset=10)
    all_names = load_modelnet_split('test')[2]
    truth = np.array([BANK_CLASSES.index(all_names[t]) for t in truth])
    rng = np.random.default_rng(14)
    z_up = [to_sensor_frame(c, rng) for c in xyz]
    # The same points as a depth camera reports them: x right, y down, z forward.
    optical = [np.ascontiguousarray(np.stack([-c[:, 1], -c[:, 2], c[:, 0]], axis=1))
               for c in z_up]
    keys = {}
    for frame, clouds, base in (('base_link', z_up, 8000), (OPTICAL, optical, 9000)):
        for i, cloud in enumerate(clouds):
            keys[frame, i] = (base + i, 0)
            _send(harness, io, cloud, keys[frame, i], frame=frame, wait=False)
            if i % 8 == 7:
                assert harness.spin_until(lambda k=keys[frame, i]: _answers(io, k),
                                          ANSWER_TIMEOUT_S), node.log()
    assert harness.spin_until(lambda: all(_answers(io, k) for k in keys.values()),
                              ANSWER_TIMEOUT_S)

    def accuracy(frame: str) -> float:
        labels = [int(decode_classifications(_answers(io, keys[frame, i])[0])['class_id'][0])
                  for i in range(len(xyz))]
        return 100.0 * float(np.mean(np.array(labels) == truth))

    acc_up, acc_optical = accuracy('base_link'), accuracy(OPTICAL)
    assert acc_up > 100.0 / len(BANK_CLASSES) + 20, acc_up        # far above chance
    assert abs(acc_up - acc_optical) <= 2.0, (acc_up, acc_optical)
    # Outputs stay in the input frame: the centroid of an optical-frame answer is optical.
    res = decode_classifications(_answers(io, keys[OPTICAL, 0])[0])
    np.testing.assert_allclose(res['centroid'][0], optical[0].mean(axis=0), atol=1e-4)


def test_4mb_organised_cloud_is_answered_at_default_qos(harness: Harness, node: NodeProcess,
                                                        io: dict) -> None:
    """A 640x480 organised cloud (x, y, z, rgb: 4.9 MB) over a reliable (default) reader."""
    rng = np.random.default_rng(15)
    obj = to_sensor_frame(pick('test', ('bottle',), 1)[0][0], rng)
    h, w = 480, 640
    grid = np.full((h * w, 3), np.nan, np.float32)            # invalid depth: NaN
    valid = rng.choice(h * w, 60_000, replace=False)
    grid[valid] = obj[rng.integers(0, len(obj), len(valid))] + rng.normal(
        0, 0.002, (len(valid), 3)).astype(np.float32)
    msg = cloud_msg(grid, 'camera_link', stamp(7300),
                    {'rgb': rng.random(h * w, dtype=np.float32)})
    msg.height, msg.width, msg.row_step = h, w, w * msg.point_step
    assert len(msg.data) >= 4_000_000
    io['pub'].publish(msg)
    assert harness.spin_until(lambda: _answers(io, (7300, 0)), ANSWER_TIMEOUT_S), node.log()


def test_silent_topic_turns_diagnostics_warn(harness: Harness, io: dict) -> None:
    harness.spin_for(INPUT_TIMEOUT_S + 1.5)
    silent = latest_diagnostics(io['diag'], f': input /{SILENT}')
    assert silent['_level'] == '1' and 'no publisher' in silent['_message'], silent
    assert latest_diagnostics(io['diag'], f': input /{TOPIC}')['_level'] in ('0', '1')
    assert f'no publisher on /{SILENT}' in latest_diagnostics(io['diag'])['_message']


def test_cleanup_frees_and_shutdown_exits(harness: Harness, node: NodeProcess, io: dict) -> None:
    assert _lifecycle(harness, 'deactivate')
    assert _lifecycle(harness, 'cleanup')
    assert _state(harness) == 'unconfigured'
    assert 'bank released' in node.log()
    assert _lifecycle(harness, 'configure')          # configurable again after cleanup
    assert _state(harness) == 'inactive'
    assert node.stop() == 0
    assert 'Traceback' not in node.log()
