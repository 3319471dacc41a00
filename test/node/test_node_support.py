"""ROS-free parts of the classifier node: stats, rate-limited logging, markers, parameters."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.node.markers import MarkerTracker, box_line_points, class_colour, object_box
from point_gn_ros.node.stats import LatencyWindow, NodeStats, RateMeter
from point_gn_ros.node.rate_limited_log import RateLimitedLogger, RateLimiter

REPO = Path(__file__).resolve().parents[2]


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_rate_meter_sliding_window() -> None:
    clock = FakeClock()
    meter = RateMeter(window_s=2.0, clock=clock)
    for _ in range(20):
        clock.t += 0.1
        meter.add()
    assert meter.rate() == pytest.approx(10.0, rel=0.11)
    clock.t += 5.0
    assert meter.rate() == 0.0


def test_latency_percentiles() -> None:
    lw = LatencyWindow(maxlen=100)
    assert all(math.isnan(v) for v in lw.percentiles_ms())
    for ms in range(1, 101):
        lw.add(ms / 1000)
    p50, p99 = lw.percentiles_ms()
    assert p50 == pytest.approx(50.5) and p99 == pytest.approx(99.01)


def test_node_stats_snapshot() -> None:
    stats = NodeStats(num_topics=2)
    stats.on_received(0)
    stats.on_received(1)
    stats.on_received(1)
    stats.on_rejected('missing field')
    stats.on_rejected('missing field')
    stats.on_rejected('too few points')
    stats.on_skipped_segments(3)
    stats.on_batch(4)
    stats.on_published(1, 3, 0.010, None)
    stats.on_published(0, 1, 0.030, 0.050)
    snap = stats.snapshot(queue_depths=[1, 2])
    assert snap.received == [1, 2] and snap.processed == [1, 1] and snap.objects == 4
    assert snap.rejected == {'missing field': 2, 'too few points': 1}
    assert snap.dropped == [0, 0] and snap.queue_depths == [1, 2]
    assert snap.skipped_segments == 3 and snap.batch_size_mean == 4.0
    assert snap.latency_receipt_ms[0] == pytest.approx(20.0)
    assert snap.latency_stamp_ms[0] == pytest.approx(50.0) and snap.latency_samples == 2


def test_rate_limited_logger_one_per_key_per_period_with_suppressed_count() -> None:
    clock, lines = FakeClock(), []
    log = RateLimitedLogger(lines.append, period_s=5.0, clock=clock)
    assert log('a', 'bad 1')
    assert not log('a', 'bad 2')
    assert not log('a', 'bad 3')
    assert log('b', 'other topic')            # keys are independent
    clock.t += 5.0
    assert log('a', 'bad 4')
    assert lines == ['bad 1', 'other topic',
                     'bad 4 (2 similar message(s) suppressed since the last report)']
    limiter = RateLimiter(1.0, clock)
    assert limiter.check('k') == (True, 0)


def test_marker_tracker_deletes_stale_ids_per_topic() -> None:
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker

    rng = np.random.default_rng(0)
    boxes = [object_box(rng.normal(size=(50, 3)).astype(np.float32) + i, f'c{i}', i, 0.5)
             for i in range(3)]
    tracker = MarkerTracker(['/ns/front', 'rear'])
    first = tracker.build(0, Header(frame_id='f'), boxes)
    assert [m.action for m in first.markers] == [Marker.ADD] * 6
    assert {m.ns for m in first.markers} == {'ns_front/labels', 'ns_front/boxes'}
    text = first.markers[0]
    assert text.type == Marker.TEXT_VIEW_FACING and text.text == 'c0 0.50'
    assert text.pose.position.z > boxes[0].hi[2] and text.header.frame_id == 'f'
    assert first.markers[1].type == Marker.LINE_LIST and len(first.markers[1].points) == 24
    other = tracker.build(1, Header(), boxes[:1])          # another topic: no deletes there
    assert all(m.action == Marker.ADD for m in other.markers)
    second = tracker.build(0, Header(frame_id='f'), boxes[:1])
    deleted = sorted((m.ns, m.id) for m in second.markers if m.action == Marker.DELETE)
    assert deleted == [('ns_front/boxes', 1), ('ns_front/boxes', 2),
                       ('ns_front/labels', 1), ('ns_front/labels', 2)]
    third = tracker.build(0, Header(), [])
    assert sorted((m.ns, m.id) for m in third.markers) == [('ns_front/boxes', 0),
                                                           ('ns_front/labels', 0)]


def test_box_geometry_and_colours() -> None:
    pts = np.array(box_line_points((0, 0, 0), (1, 2, 3)))
    assert pts.shape == (24, 3)
    assert set(map(tuple, pts)) == {(x, y, z) for x in (0, 1) for y in (0, 2) for z in (0, 3)}
    edges = pts.reshape(12, 2, 3)
    assert (np.count_nonzero(edges[:, 0] != edges[:, 1], axis=1) == 1).all()  # axis-aligned
    assert class_colour(-1) == (0.6, 0.6, 0.6)
    assert len({class_colour(i) for i in range(40)}) == 40


def test_reason_keys_are_short_and_bounded() -> None:
    from point_gn_ros.node.pipeline import reason_key as _reason_key
    assert _reason_key("missing field 'z' (fields: x, y)") == 'missing field'
    assert _reason_key('data has 100 bytes, expected row_step*height = 120') == 'data has bytes'
    assert (_reason_key("field 'x' (offset 8, 4 bytes) does not fit in point_step 8")
            == 'field does not fit in point_step')
    assert _reason_key('') == 'malformed'


def test_config_yaml_lists_every_parameter_with_its_default() -> None:
    yaml = pytest.importorskip('yaml')   # comes with the ROS Python packages

    from point_gn_ros.node.classifier_node import PARAMETERS
    from point_gn_ros.node.enrollment import ENROLL_PARAMETERS
    params = yaml.safe_load((REPO / 'config' / 'classifier.yaml').read_text())
    values = params['/**']['ros__parameters']
    assert set(values) == set(PARAMETERS) | set(ENROLL_PARAMETERS)
    for name, (default, description, _) in (PARAMETERS | ENROLL_PARAMETERS).items():
        assert values[name] == default, name
        assert description


def test_marker_lifetime() -> None:
    from std_msgs.msg import Header

    box = object_box(np.zeros((4, 3), np.float32), 'c', 0, 0.5)
    markers = MarkerTracker(['t']).build(0, Header(), [box], lifetime_s=1.25).markers
    assert [(m.lifetime.sec, m.lifetime.nanosec) for m in markers] == [(1, 250_000_000)] * 2
    forever = MarkerTracker(['t']).build(0, Header(), [box]).markers
    assert all(m.lifetime.sec == 0 and m.lifetime.nanosec == 0 for m in forever)


def test_stamp_latency_only_with_comparable_clocks() -> None:
    from point_gn_ros.node.classifier_node import stamp_latency_s

    assert stamp_latency_s(5_000_000_000, 4_000_000_000) == pytest.approx(1.0)
    assert stamp_latency_s(0, 4_000_000_000) is None       # sim time before the first /clock
    assert stamp_latency_s(5_000_000_000, 0) is None       # unstamped message


def test_parameter_validation_and_closest_names() -> None:
    from point_gn_ros.node.params import (LIVE, PARAMETERS, NodeConfigError, closest_parameter,
                                          settings_from_values)

    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    s = settings_from_values(values)
    assert s.qos_reliability == 'auto' and s.up_axis == 'auto' and s.autostart
    with pytest.raises(NodeConfigError, match='up_axis'):
        settings_from_values(values | {'up_axis': 'up'})
    with pytest.raises(NodeConfigError, match='repeats'):
        settings_from_values(values | {'input_topics': ['a', 'a']})
    assert closest_parameter('unkown_threshold', PARAMETERS) == 'unknown_threshold'
    assert closest_parameter('input_topic', PARAMETERS) == 'input_topics'
    assert closest_parameter('zzz', PARAMETERS) is None
    assert LIVE <= set(PARAMETERS)


def test_input_watchdog_names_silent_topics() -> None:
    from point_gn_ros.node.watchdog import InputWatchdog

    dog = InputWatchdog(3, now=0.0)
    names = ['/a', '/b', '/c']
    assert dog.problems(names, [1, 0, 1], 5.0, now=4.0) == ['', '', '']      # grace period
    dog.on_message(0, now=5.5)
    assert dog.problems(names, [1, 0, 1], 5.0, now=6.0) == [
        '', 'no publisher on /b for 6 s', 'no message on /c for 6 s']
    assert dog.problems(names, [1, 1, 1], 5.0, now=6.5)[1] == 'no message on /b for 6 s'
    assert dog.problems(names, [0, 0, 0], 0.0, now=100.0) == ['', '', '']    # 0 = off


def test_frozen_start_up_objects_are_skipped_by_full_collections() -> None:
    import gc
    import weakref

    from point_gn_ros.node.gc_pauses import freeze_startup_objects, thaw

    class Cycle:
        pass

    def cycle() -> Cycle:
        a, b = Cycle(), Cycle()
        a.other, b.other = b, a            # only the cyclic collector frees these
        return a

    try:
        held = cycle()                     # alive at the freeze, garbage after it
        old = weakref.ref(held)
        assert freeze_startup_objects() > 0
        del held
        new = weakref.ref(cycle())
        gc.collect()
        assert new() is None               # made after the freeze: collected as before
        assert old() is not None           # frozen: a full collection skipped it
        thaw()
        assert gc.get_freeze_count() == 0
        gc.collect()
        assert old() is None               # thawed: collected again
    finally:
        thaw()
