"""The node's fit to the graph without DDS: per-topic settings, 'no segment' ids, QoS choice.

The DDS side (publishers of either reliability answered, the incompatible-QoS diagnostic,
a topic served without the segment field) is test/test_node_qos.py.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from point_gn_ros.node.input_qos import InputQoS, choose_reliability, incompatible
from point_gn_ros.node.params import (PARAMETERS, NodeConfigError, NoSegment,
                                      settings_from_values, topic_key,
                                      unknown_override_warnings)
from point_gn_ros.pointcloud2 import decode_xyz, xyz_to_pointcloud2

DEFAULTS = {name: default for name, (default, _, _) in PARAMETERS.items()}


def _pub(reliability: str) -> SimpleNamespace:
    return SimpleNamespace(qos_profile=SimpleNamespace(
        reliability=SimpleNamespace(name=reliability.upper())))


def test_per_topic_settings_override_the_nodes() -> None:
    values = DEFAULTS | {'input_topics': ['/lidar/clusters', 'camera/objects'],
                         'segment_field': 'label'}
    s = settings_from_values(values, {'topics.lidar.clusters.segment_field': '',
                                      'topics.lidar.clusters.qos_reliability': 'best_effort',
                                      'topics.camera.objects.up_axis': '-y'})
    assert topic_key('/lidar/clusters') == 'lidar.clusters'
    lidar, camera = s.topic(0), s.topic(1)
    assert (lidar.segment_field, lidar.up_axis, lidar.qos_reliability) == (
        '', 'auto', 'best_effort')
    assert (camera.segment_field, camera.up_axis, camera.qos_reliability) == (
        'label', '-y', 'auto')
    # Without overrides every topic has the node's settings.
    plain = settings_from_values(values)
    assert plain.topic(1).segment_field == 'label' and plain.topic(0).up_axis == 'auto'


@pytest.mark.parametrize(('name', 'value', 'match'), [
    ('topics.nowhere.segment_field', '', 'no input topic'),
    ('topics.segmented_objects.segment_feild', 'x', "did you mean 'segment_field'"),
    ('topics.segmented_objects.up_axis', 'up', 'must be one of'),
    ('topics.segmented_objects.qos_reliability', 'fast', 'must be one of'),
])
def test_bad_per_topic_settings_are_one_clear_error(name: str, value: str, match: str) -> None:
    with pytest.raises(NodeConfigError, match=match):
        settings_from_values(DEFAULTS, {name: value})


def test_topic_parameters_are_not_taken_for_misspellings() -> None:
    assert unknown_override_warnings(['topics.a.b.segment_field']) == []
    assert unknown_override_warnings(['segmnt_field'])[0].endswith("'segment_field'?")


def test_no_segment_ids_parse_and_refuse_junk() -> None:
    assert NoSegment.parse(['negative', 'max']) == NoSegment(True, True, frozenset())
    assert NoSegment.parse(['0', '0xFFFF']) == NoSegment(False, False, frozenset({0, 65535}))
    with pytest.raises(NodeConfigError, match='no_segment_ids'):
        settings_from_values(DEFAULTS | {'no_segment_ids': ['negativ']})


@pytest.mark.parametrize('dtype', [np.uint32, np.uint16, np.uint8])
def test_unsigned_type_max_is_unsegmented(dtype: type) -> None:
    """PCL's uint32 0xFFFFFFFF (and uint16 65535) "no label" is not an object, nor an error."""
    from point_gn_ros.pointcloud2 import split_segments

    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(300, 3)).astype(np.float32)
    ids = np.repeat(np.array([0, 1, np.iinfo(dtype).max], dtype=dtype), 100)
    msg = xyz_to_pointcloud2(None, xyz, {'label': ids})
    decoded = decode_xyz(msg, ('label',))
    no_seg = NoSegment.parse(DEFAULTS['no_segment_ids'])
    parts = split_segments(decoded, 'label', skip_negative=no_seg.negative,
                           skip_type_max=no_seg.type_max, skip_ids=no_seg.ids)
    assert [seg for seg, _ in parts] == [0, 1]
    assert all(len(part) == 100 for _, part in parts)


def test_auto_reliability_follows_the_publishers() -> None:
    assert choose_reliability('auto', [], None) == 'reliable'
    assert choose_reliability('auto', [_pub('reliable')], 'best_effort') == 'reliable'
    assert choose_reliability('auto', [_pub('reliable'), _pub('best_effort')],
                              'reliable') == 'best_effort'
    # Publishers gone: keep what the subscription has (no churn).
    assert choose_reliability('auto', [], 'best_effort') == 'best_effort'
    assert choose_reliability('reliable', [_pub('best_effort')], None) == 'reliable'
    assert incompatible([_pub('best_effort'), _pub('reliable')], 'reliable') == [
        'publisher best_effort, subscription reliable']
    assert incompatible([_pub('best_effort')], 'best_effort') == []

    qos = InputQoS(['reliable'])
    assert qos.choose(0, [_pub('best_effort')]) is None         # fixed: never switches
    assert qos.observe(0, [_pub('best_effort')]) == [
        'publisher best_effort, subscription reliable']
    assert qos.observe(0, [_pub('best_effort')]) == []          # warned once
    qos.on_event(0, 1)
    assert qos.problem(0) == ('1 of 1 publisher(s) with incompatible QoS (publisher '
                              'best_effort, subscription reliable)')
    assert qos.values(0)['incompatible_qos_events'] == 1


def test_fuzz_client_honours_ros_domain_id(monkeypatch: pytest.MonkeyPatch) -> None:
    from point_gn_ros.clients.fuzz import default_domain_id

    monkeypatch.setenv('ROS_DOMAIN_ID', '46')
    assert default_domain_id() == 46
    monkeypatch.delenv('ROS_DOMAIN_ID')
    assert 150 <= default_domain_id() <= 230


def test_default_is_a_bank_name(tmp_path: object, capsys: pytest.CaptureFixture[str]) -> None:
    from point_gn_ros.bank.store import default_bank_path
    from point_gn_ros.cli import main as cli_main
    from point_gn_ros.commands.enroll_cmd import resolve_bank
    from point_gn_ros.errors import BankError

    assert cli_main(['bank', 'path']) == 0
    assert capsys.readouterr().out.strip() == str(default_bank_path())
    assert resolve_bank('default') == default_bank_path()
    assert resolve_bank('default', 'out.npz') == default_bank_path()
    with pytest.raises(BankError, match='-o OUT'):
        resolve_bank('default', None)          # the shipped bank is never rewritten


def test_worker_counts_numeric_errors_instead_of_logging_them() -> None:
    """A numpy overflow in the worker (here in its observe hook) is counted, not warned."""
    import threading
    import warnings

    from point_gn_ros.node.pipeline import Pipeline
    from point_gn_ros.node.stats import NodeStats
    from point_gn_ros.node.work_queue import WorkQueue
    from point_gn_ros.recognizer import Recognizer

    stats, stop = NodeStats(1), threading.Event()
    queue: WorkQueue = WorkQueue(1, 10)
    pipe = Pipeline(Recognizer.from_bank(None), settings_from_values(DEFAULTS), stats,
                    lambda key, text: None, stop)
    big = np.full(4, 3e38, np.float32)
    pipe.observe = lambda jobs: big * np.float32(10)      # overflow: inf, RuntimeWarning
    answers: list = []
    rng = np.random.default_rng(0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        worker = threading.Thread(target=pipe.serve, args=(queue, answers.append))
        worker.start()
        stats.on_received(0)
        queue.put(0, xyz_to_pointcloud2(None, rng.normal(size=(200, 3)).astype(np.float32)))
        for _ in range(600):
            if answers:
                break
            stop.wait(0.05)
        stop.set()
        queue.close()
        worker.join(10)
    assert answers, 'the message was not answered'
    assert stats.snapshot([0]).numeric_warnings >= 1
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], caught


def test_launched_node_stops_when_its_parent_dies(tmp_path: object) -> None:
    """node/parent_death.py: the child gets SIGTERM when the process that started it exits.

    `ros2 launch` exits on SIGTERM without stopping its processes; this stands in for it.
    """
    import os
    import subprocess
    import sys
    import time

    child = ('import time; from point_gn_ros.node.parent_death import exit_with_parent; '
             'assert exit_with_parent(); print("ready", flush=True); time.sleep(60)')
    parent = ('import subprocess, sys; '
              f'p = subprocess.Popen([sys.executable, "-c", {child!r}], '
              'stdout=subprocess.PIPE, text=True); '
              'print(p.pid, flush=True); assert p.stdout.readline().strip() == "ready"')
    out = subprocess.run([sys.executable, '-c', parent], capture_output=True, text=True,
                         timeout=60, env=dict(os.environ, POINT_GN_EXIT_WITH_PARENT='1'))
    assert out.returncode == 0, out.stderr
    pid = int(out.stdout.split()[0])

    def alive() -> bool:
        try:
            state = open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()[0]
        except OSError:
            return False
        return state not in ('Z', 'X')
    end = time.monotonic() + 10
    while alive() and time.monotonic() < end:
        time.sleep(0.05)
    stopped = not alive()
    if not stopped:
        os.kill(pid, 9)
    assert stopped, 'the child outlived its parent'
