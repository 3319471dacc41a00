"""`point_gn replay` on foreign bags: no ground truth, a lidar layout, mcap and sqlite3.

The bags are written here with `rosbags`, laid out as a lidar clustering pipeline publishes:
x/y/z/intensity FLOAT32, ring UINT16, time FLOAT32, 32-byte points, frame `velodyne`, no
labels; one cloud per cluster on /lidar/clusters (two clusters of a scan share its stamp),
or one labelled cloud (UINT32 `label`, 0xFFFFFFFF = no cluster) on /lidar/segmented.
Offline and through a live node: exit 0 and one answer per object in the JSON.
"""

from __future__ import annotations

from collections.abc import Iterator
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from node_testing import (DOMAIN_ID, TEST_NUM_POINTS, NodeProcess, pick, tiny_bank,
                          to_sensor_frame)
from point_gn_ros.cli import main as cli_main

__all__ = ['tiny_bank']

CLUSTERS, SEGMENTED = '/lidar/clusters', '/lidar/segmented'
NODE = 'any_bag_classifier'
LIDAR = np.dtype({'names': ['x', 'y', 'z', 'intensity', 'ring', 'time', 'label'],
                  'formats': ['<f4', '<f4', '<f4', '<f4', '<u2', '<f4', '<u4'],
                  'offsets': [0, 4, 8, 16, 20, 24, 28], 'itemsize': 32})


def _lidar_msg(typestore: object, stamp_ns: int, xyz: np.ndarray,
               label: np.ndarray | None) -> object:
    t = typestore.types
    rec = np.zeros(len(xyz), LIDAR)
    rec['x'], rec['y'], rec['z'] = xyz.T
    rec['intensity'] = 0.5
    rec['ring'] = np.arange(len(xyz)) % 32
    rec['time'] = np.linspace(0, 0.1, len(xyz))
    names = ['x', 'y', 'z', 'intensity', 'ring', 'time'] + (['label'] if label is not None
                                                             else [])
    if label is not None:
        rec['label'] = label
    datatypes = {'<f4': 7, '<u2': 4, '<u4': 6}
    fields = [t['sensor_msgs/msg/PointField'](
        name=n, offset=LIDAR.fields[n][1], datatype=datatypes[LIDAR.fields[n][0].str],
        count=1) for n in names]
    return t['sensor_msgs/msg/PointCloud2'](
        header=t['std_msgs/msg/Header'](
            stamp=t['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9,
                                                   nanosec=stamp_ns % 10**9),
            frame_id='velodyne'),
        height=1, width=len(xyz), fields=fields, is_bigendian=False, point_step=32,
        row_step=32 * len(xyz), data=rec.view(np.uint8).reshape(-1), is_dense=True)


def write_lidar_bag(path: Path, storage: str, segmented: bool,
                    topic: str | None = None) -> tuple[Path, int]:
    """Three scans; returns (bag, objects). Clusters: 2 messages a scan, one stamp."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    rng = np.random.default_rng(5)
    xyz, _ = pick('test', ('chair', 'airplane', 'lamp'), 2)
    clouds = [to_sensor_frame(c, rng) for c in xyz]
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == 'mcap'
                    else StoragePlugin.SQLITE3)
    writer.open()
    topic = topic or (SEGMENTED if segmented else CLUSTERS)
    conn = writer.add_connection(topic, 'sensor_msgs/msg/PointCloud2', typestore=store)
    t0, objects = 1_700_000_000 * 10**9, 0
    for scan in range(3):
        stamp = t0 + scan * 100_000_000
        pair = clouds[2 * scan:2 * scan + 2]
        if segmented:
            clutter = rng.uniform(-10, 10, (300, 3)).astype(np.float32)
            label = np.concatenate([np.full(len(pair[0]), 0), np.full(len(pair[1]), 1),
                                    np.full(len(clutter), 0xFFFFFFFF)]).astype(np.uint32)
            msg = _lidar_msg(store, stamp, np.concatenate([*pair, clutter]), label)
            writer.write(conn, stamp, store.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
        else:
            for j, cloud in enumerate(pair):
                msg = _lidar_msg(store, stamp, cloud, None)
                writer.write(conn, stamp + j * 1000,
                             store.serialize_cdr(msg, 'sensor_msgs/msg/PointCloud2'))
        objects += 2
    writer.close()
    return path, objects


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, int]]:
    root = tmp_path_factory.mktemp('lidar_bags')
    return {'clusters_mcap': write_lidar_bag(root / 'clusters_mcap', 'mcap', False),
            'segmented_sqlite3': write_lidar_bag(root / 'seg_sqlite3', 'sqlite3', True),
            'clusters_sqlite3': write_lidar_bag(root / 'clusters_sqlite3', 'sqlite3', False),
            'segmented_mcap': write_lidar_bag(root / 'seg_mcap', 'mcap', True)}


def _run(args: list[str]) -> None:
    assert cli_main(args) == 0


@pytest.mark.parametrize('name', ['clusters_mcap', 'segmented_sqlite3', 'clusters_sqlite3',
                                  'segmented_mcap'])
def test_offline_answers_every_object(bags: dict, tiny_bank: Path, tmp_path: Path,
                                      name: str) -> None:
    bag, objects = bags[name]
    out, table = tmp_path / 'a.json', tmp_path / 'a.csv'
    _run(['replay', str(bag), '--offline', '--bank', str(tiny_bank), '--segment-field',
          'label', '--json', str(out), '--csv', str(table), '--quiet',
          '--output-bag', str(tmp_path / 'out_bag')])
    doc = json.loads(out.read_text())
    from rosbags.rosbag2 import Reader

    from point_gn_ros.pointcloud2 import decode_classifications
    with Reader(tmp_path / 'out_bag') as reader:
        store = __import__('point_gn_ros.bag.reader', fromlist=['_typestore'])._typestore()
        answers = [decode_classifications(store.deserialize_cdr(raw, c.msgtype))
                   for c, _, raw in reader.messages()
                   if c.topic == '/point_gn/classifications']
        inputs = sum(i.msgcount for t, i in reader.topics.items() if t.startswith('/lidar/'))
    assert inputs == doc['summary']['messages']
    assert sum(len(a['class_id']) for a in answers) == objects
    assert doc['mode'] == 'offline' and len(doc['answers']) == objects
    assert all(a['stamp_ns'] > 0 and a['label'] and a['frame_id'] == 'velodyne'
               for a in doc['answers'])
    assert doc['summary']['objects'] == objects
    segmented = name.startswith('segmented')
    assert {a['segment'] for a in doc['answers']} == ({0, 1} if segmented else {-1})
    rows = list(csv.DictReader(table.open()))
    assert len(rows) == objects and rows[0]['topic'] in (CLUSTERS, SEGMENTED)


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': [CLUSTERS, SEGMENTED],
                        'topics.lidar.segmented.segment_field': 'label'},
                       tmp_path_factory.mktemp('node') / 'node.log', node_name=NODE)
    try:
        yield proc
    finally:
        proc.stop()


@pytest.mark.parametrize('name', ['clusters_mcap', 'segmented_sqlite3'])
def test_live_answers_every_object_like_offline(bags: dict, tiny_bank: Path, tmp_path: Path,
                                                node: NodeProcess, name: str,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv('ROS_DOMAIN_ID', str(DOMAIN_ID))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    bag, objects = bags[name]
    out, out_bag = tmp_path / 'live.json', tmp_path / 'with_answers'
    code = cli_main(['replay', str(bag), '--node-name', NODE, '--rate', '2', '--json', str(out),
                     '--output-bag', str(out_bag), '--discovery-timeout', '90', '--quiet'])
    assert code == 0, node.log()
    live = json.loads(out.read_text())
    assert live['mode'] == 'live' and live['sent'] == live['summary']['messages']
    assert len(live['answers']) == objects, node.log()
    assert all(a['latency_ms'] > 0 for a in live['answers'])
    _run(['replay', str(bag), '--offline', '--bank', str(tiny_bank), '--segment-field',
          'label', '--json', str(tmp_path / 'off.json'), '--quiet'])
    offline = json.loads((tmp_path / 'off.json').read_text())
    key = lambda a: (a['stamp_ns'], a['segment'], a['label'])  # noqa: E731
    assert sorted(map(key, live['answers'])) == sorted(map(key, offline['answers']))
    # Clusters of one scan share its stamp: matched to their own message in send order.
    where = {(a['message'], a['segment']): a for a in offline['answers']}
    for a in live['answers']:                    # the object's centroid, input frame, both
        mine = where[a['message'], a['segment']]
        assert a['label'] == mine['label']
        assert a['centroid'] == pytest.approx(mine['centroid'], abs=1e-3)

    from rosbags.rosbag2 import Reader
    with Reader(out_bag) as reader:
        counts = {t: i.msgcount for t, i in reader.topics.items()}
    assert counts[f'/{NODE}/classifications'] == live['sent']
    from point_gn_ros.node.outputs import vision_msgs_available
    if vision_msgs_available():          # the node publishes them: they go in as well
        assert counts[f'/{NODE}/detections'] == live['sent']
    assert sum(n for t, n in counts.items() if t.startswith('/lidar/')) == live['sent']


def test_bag_play_publishes_at_the_recorded_rate(tmp_path: Path) -> None:
    """`point_gn bag play` (no ros2 bag): every message, paced by the recorded times."""
    import subprocess
    import sys
    import time

    from sensor_msgs.msg import PointCloud2

    from node_testing import REPO, Harness, sensor_qos

    topic = '/bag_play_test/clusters'              # no node of this module listens there
    bag, _ = write_lidar_bag(tmp_path / 'play', 'mcap', False, topic)
    harness = Harness('bag_play_test')
    try:
        got = harness.collect(PointCloud2, topic, sensor_qos())
        env = dict(__import__('os').environ, ROS_DOMAIN_ID=str(DOMAIN_ID),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
        t0 = time.monotonic()
        player = subprocess.Popen([sys.executable, '-m', 'point_gn_ros.cli', 'bag', 'play',
                                   str(bag), '--rate', '0.5', '--topics', topic,
                                   '--wait-for-subscribers', '60'],
                                  env=env, cwd=REPO,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert harness.spin_until(lambda: len(got) == 6 or player.poll() not in (None, 0),
                                  60.0), player.communicate()
        assert player.wait(30) == 0
        # 3 scans 0.1 s apart at half speed: the last message ~0.4 s after the first.
        stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in got]
        assert stamps == sorted(stamps) and len(set(stamps)) == 3
        assert time.monotonic() - t0 > 0.4
        assert all(m.header.frame_id == 'velodyne' and m.point_step == 32 for m in got)
    finally:
        harness.close()


def test_bag_info_lists_a_foreign_bags_clouds(bags: dict,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    _run(['bag', 'info', str(bags['clusters_mcap'][0])])
    out = capsys.readouterr().out
    assert 'no ground truth' in out and f'{CLUSTERS} 6' in out
