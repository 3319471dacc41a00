"""`point_gn replay` exits non-zero when the node does not answer or answers twice.

Stand-in classifiers (plain rclpy nodes in this process, no model) on a private ROS domain:
one that never answers, and two with the same name that both answer every message.
"""

from __future__ import annotations

from collections.abc import Iterator
import random
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import ArrayDataset

from point_gn_ros.bag.writer import WriteOptions, write_bag
from point_gn_ros.cli import main as cli_main
from point_gn_ros.commands.bag_cmd import replay_problems

DOMAIN_ID = random.randint(100, 200)
TOPIC = '/replay_fault_objects'
NAME = 'fake_classifier'


class FakeClassifiers:
    """`copies` nodes named NAME on TOPIC; each answers every message unless `silent`."""

    def __init__(self, copies: int, silent: bool) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for _ in range(copies):
            node = rclpy.create_node(NAME, context=self.context)
            pub = node.create_publisher(PointCloud2, f'/{NAME}/classifications', 10)
            names = node.create_publisher(String, f'/{NAME}/class_names', latched)
            names.publish(String(data='\n'.join(f'c{i}' for i in range(3))))
            node.create_subscription(PointCloud2, TOPIC,
                                     lambda msg, p=pub: None if silent else p.publish(
                                         self._answer(msg)), 10)
            self.executor.add_node(node)
            self.nodes.append(node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    @staticmethod
    def _answer(msg: Any) -> Any:
        from point_gn_ros.pointcloud2 import make_classifications
        return make_classifications(msg.header, np.zeros((1, 3)), [0], [0.9], [[0]], [[0.9]],
                                    -1, 0)

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setenv('ROS_DOMAIN_ID', str(DOMAIN_ID))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    yield


def _bag(tmp_path: Path, n: int = 6) -> Path:
    rng = np.random.default_rng(0)
    ds = ArrayDataset(rng.normal(size=(n, 64, 3)).astype(np.float32), np.arange(n) % 3,
                      [f'c{i}' for i in range(3)], split='test')
    return write_bag(ds, tmp_path / 'bag', WriteOptions(topic=TOPIC, rate_hz=20)).path


def _replay(bag: Path, tmp_path: Path, *extra: str) -> tuple[int, dict]:
    import json
    out = tmp_path / 'report.json'
    code = cli_main(['replay', str(bag), '--node-name', NAME, '--timeout', '2',
                     '--discovery-timeout', '30', '--json', str(out), '--quiet', *extra])
    return code, json.loads(out.read_text())


def test_a_node_that_never_answers_fails_the_replay(ros_domain: None, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    fakes = FakeClassifiers(1, silent=True)
    try:
        code, report = _replay(_bag(tmp_path), tmp_path)
    finally:
        fakes.close()
    assert code == 1 and report['answered'] == 0 and report['sent'] == 6
    err = capsys.readouterr().err
    assert 'point_gn: replay: answered 0 of 6 message(s): is the node classifying' in err


def test_two_nodes_answering_twice_are_detected(ros_domain: None, tmp_path: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    fakes = FakeClassifiers(2, silent=False)
    try:
        code, report = _replay(_bag(tmp_path), tmp_path, '--lockstep')
    finally:
        fakes.close()
    assert report['answered'] == 6
    assert report['info']['duplicate_answers'] >= 1
    assert report['info']['classification_publishers'] == 2
    assert code == 1
    err = capsys.readouterr().err
    assert 'duplicate answer(s): more than one node answers' in err
    assert '2 publishers on /fake_classifier/classifications' in err


def test_min_answered_share() -> None:
    base = {'sent': 10, 'answered': 7, 'topic': '/t', 'info': {}}
    assert replay_problems(base) == []
    assert replay_problems(base, 0.7) == []
    assert replay_problems(base, 0.8) == ['answered 7 of 10 message(s), less than '
                                          '--min-answered 0.8']
    assert replay_problems({**base, 'answered': 0})[0].startswith('answered 0 of 10')
    assert replay_problems({**base, 'sent': 0, 'answered': 0}) == []


def test_min_answered_out_of_range_is_one_error(tmp_path: Path,
                                               capsys: pytest.CaptureFixture) -> None:
    assert cli_main(['replay', str(tmp_path), '--min-answered', '1.5']) == 2
    assert '--min-answered must be a share' in capsys.readouterr().err
