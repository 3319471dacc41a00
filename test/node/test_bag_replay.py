"""`point_gn replay` through a real classifier node over Fast DDS, checked against --offline.

Two node processes share one private ROS domain (random 100..200, so that concurrent test
sessions on this machine do not meet): one classifies single-object messages on
/segmented_objects, the other segmented messages on /multi_objects.
"""

from __future__ import annotations

from collections.abc import Iterator
import json
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import threading
import time
from typing import Any

import pytest

from conftest import ArrayDataset, load_modelnet_subset
from point_gn_ros.bag.realism import Realism
from point_gn_ros.bag.writer import WriteOptions, write_bag
from point_gn_ros.cli import main as cli_main

REPO = Path(__file__).resolve().parents[2]
DOMAIN_ID = int(os.environ.get('ROS_DOMAIN_ID') or random.randint(100, 200))  # caller's first
MULTI_TOPIC = '/multi_objects'
SINGLE_NODE, MULTI_NODE = 'bag_test_classifier', 'bag_test_multi_classifier'
OBJECTS = 10


@pytest.fixture(scope='module')
def ros_env() -> Iterator[dict[str, str]]:
    env = {'ROS_DOMAIN_ID': str(DOMAIN_ID), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    with pytest.MonkeyPatch.context() as mp:
        for key, value in env.items():
            mp.setenv(key, value)
        yield dict(os.environ)


class _Node:
    """`python -m point_gn_ros.node.classifier_node` in its own process, output in a log file."""

    def __init__(self, name: str, params: dict[str, str], log: Path, env: dict[str, str]) -> None:
        args = [sys.executable, '-m', 'point_gn_ros.node.classifier_node', '--ros-args',
                '-r', f'__node:={name}']
        for key, value in params.items():
            args += ['-p', f'{key}:={value}']
        self.log_path = log
        self._log = open(log, 'wb')  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT,
                                     env=env | {'PYTHONUNBUFFERED': '1'}, cwd=REPO)

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()


@pytest.fixture(scope='module')
def nodes(ros_env: dict[str, str], small_bank_path: Path,
          tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, _Node]]:
    logs = tmp_path_factory.mktemp('node_logs')
    started: dict[str, _Node] = {}
    try:
        started['single'] = _Node(SINGLE_NODE, {'bank_path': str(small_bank_path)},
                                  logs / 'single.log', ros_env)
        started['multi'] = _Node(MULTI_NODE, {
            'bank_path': str(small_bank_path), 'input_topics': f'[{MULTI_TOPIC}]',
            'segment_field': 'segment'}, logs / 'multi.log', ros_env)
        yield started
    finally:
        for node in started.values():
            node.stop()


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    xyz, labels, names = load_modelnet_subset('test', 1)
    ds = ArrayDataset(xyz[:OBJECTS], labels[:OBJECTS], names, split='test')
    root = tmp_path_factory.mktemp('bags')
    return {
        'mcap': write_bag(ds, root / 'mcap', WriteOptions(storage='mcap', rate_hz=10)).path,
        'sqlite3': write_bag(ds, root / 'sqlite3', WriteOptions(
            storage='sqlite3', rate_hz=10, seed=1,
            realism=Realism(sensor_frame=True, noise=0.003, dropout=0.1, partial=0.8))).path,
        'multi': write_bag(ds, root / 'multi', WriteOptions(
            objects_per_message=3, topic=MULTI_TOPIC, rate_hz=10)).path,
    }


def _replay(bag: Path, out: Path, *args: str, nodes: dict[str, _Node] | None = None
            ) -> dict[str, Any]:
    code = cli_main(['replay', str(bag), '--json', str(out), '--quiet', *args])
    if code != 0 and nodes:
        pytest.fail(f'replay exited {code}; node logs:\n'
                    + '\n'.join(n.log()[-3000:] for n in nodes.values()))
    assert code == 0
    return json.loads(out.read_text())


def _labels(report: dict[str, Any]) -> dict[tuple[int, int], int]:
    """(message index, segment) -> predicted class, from a report's prediction rows."""
    return {(row[0], row[2]): row[4] for row in report['predictions']}


def _check_against_offline(online: dict[str, Any], bag: Path, bank: Path, tmp: Path) -> None:
    offline = _replay(bag, tmp / 'offline.json', '--offline', '--bank', str(bank))
    assert offline['answered'] == offline['sent'] == online['sent']
    # Nothing was dropped, so the node answered every object, exactly as the library does.
    assert online['dropped'] == 0 and online['unanswered'] == 0
    assert online['objects_answered'] == offline['objects_answered'] == online['objects_sent']
    assert _labels(online) == _labels(offline)
    assert online['accuracy'] == pytest.approx(offline['accuracy'])


def test_lockstep_mcap_matches_offline(nodes: dict[str, _Node], bags: dict[str, Path],
                                       small_bank_path: Path, tmp_path: Path) -> None:
    png = tmp_path / 'lockstep'
    report = _replay(bags['mcap'], tmp_path / 'online.json', '--lockstep', '--node-name',
                     SINGLE_NODE, '--markdown', str(tmp_path / 'r.md'), '--png', str(png),
                     '--discovery-timeout', '90', nodes=nodes)
    assert (report['mode'], report['node']) == ('lockstep', '/' + SINGLE_NODE)
    assert report['sent'] == report['answered'] == OBJECTS
    lat = report['latency_ms']
    assert 0 < lat['p50'] <= lat['p90'] <= lat['p99'] <= lat['max']
    assert report['info']['node_received'] == OBJECTS   # from the node's /diagnostics
    assert (tmp_path / 'lockstep_confusion.png').stat().st_size > 0
    assert (tmp_path / 'lockstep_latency.png').stat().st_size > 0
    assert '| messages answered | 10 |' in (tmp_path / 'r.md').read_text()
    _check_against_offline(report, bags['mcap'], small_bank_path, tmp_path)


def test_rate_sqlite3_realism_matches_offline(nodes: dict[str, _Node], bags: dict[str, Path],
                                             small_bank_path: Path, tmp_path: Path) -> None:
    t0 = time.monotonic()
    # No --node-name: the replay finds the node subscribed to the bag's topic.
    report = _replay(bags['sqlite3'], tmp_path / 'online.json', '--rate', '3',
                     '--discovery-timeout', '90', nodes=nodes)
    assert report['node'] == '/' + SINGLE_NODE and report['info']['rate'] == 3
    assert report['sent'] == report['answered'] == OBJECTS
    # 10 messages recorded at 10 Hz, played at 30 Hz: ~0.3 s of sending.
    assert 0.25 < report['wall_s'] < 0.3 + 5 and time.monotonic() - t0 < 60
    _check_against_offline(report, bags['sqlite3'], small_bank_path, tmp_path)


def test_multi_object_lockstep_matches_offline(nodes: dict[str, _Node], bags: dict[str, Path],
                                               small_bank_path: Path, tmp_path: Path) -> None:
    report = _replay(bags['multi'], tmp_path / 'online.json', '--lockstep',
                     '--discovery-timeout', '90', nodes=nodes)
    assert report['node'] == '/' + MULTI_NODE
    assert (report['sent'], report['objects_sent'], report['objects_answered']) == (4, 10, 10)
    assert {seg for _, seg in _labels(report)} == {0, 1, 2}
    _check_against_offline(report, bags['multi'], small_bank_path, tmp_path)


def test_listen_only_beside_another_publisher(nodes: dict[str, _Node], bags: dict[str, Path],
                                              small_bank_path: Path, ros_env: dict[str, str],
                                              tmp_path: Path) -> None:
    from point_gn_ros.bag.reader import read_bag
    from point_gn_ros.bag.replay import ReplayOptions, run_replay
    from point_gn_ros.bag.report import build_report

    listening = threading.Event()
    out: dict[str, Any] = {}

    def log(text: str) -> None:
        if text.startswith('listening'):
            listening.set()

    def listen() -> None:
        try:
            contents = read_bag(bags['mcap'])
            result = run_replay(contents, ReplayOptions(
                mode='listen-only', timeout=10, discovery_timeout=90, log=log))
            out['report'] = build_report(contents, result)
        except BaseException as exc:  # noqa: BLE001 - handed to the test thread
            out['error'] = exc
            listening.set()

    thread = threading.Thread(target=listen, daemon=True)
    thread.start()
    assert listening.wait(120) and 'error' not in out, out.get('error')
    # Stands in for `ros2 bag play`: a separate process publishing the bag's messages.
    player = subprocess.Popen(
        [sys.executable, '-m', 'point_gn_ros.cli', 'replay', str(bags['mcap']), '--rate', '2',
         '--quiet', '--timeout', '5'], env=ros_env, cwd=REPO, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE)
    try:
        thread.join(90)
        assert not thread.is_alive(), 'listen-only replay did not finish'
        assert player.wait(60) == 0, player.stderr.read().decode() if player.stderr else ''
    finally:
        if player.poll() is None:
            player.kill()
            player.wait(5)
    assert 'error' not in out, out.get('error')
    report = out['report']
    assert report['mode'] == 'listen-only' and report['latency_ms']['p50'] is None
    assert report['sent'] == report['answered'] == OBJECTS
    offline = _replay(bags['mcap'], tmp_path / 'offline.json', '--offline', '--bank',
                      str(small_bank_path))
    assert _labels(report) == _labels(offline)


def test_no_node_is_one_clear_error(ros_env: dict[str, str], tmp_path: Path,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    xyz, labels, names = load_modelnet_subset('test', 1)
    bag = write_bag(ArrayDataset(xyz[:1], labels[:1], names), tmp_path / 'b',
                    WriteOptions(topic='/nobody_listens')).path
    assert cli_main(['replay', str(bag), '--discovery-timeout', '1']) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith('point_gn: error:') and '/nobody_listens' in err
