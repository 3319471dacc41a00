"""`point_gn bag write` / bag reading without a ROS graph: layout, realism and bad bags."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from conftest import ArrayDataset, load_modelnet_subset
from point_gn_ros.bag import CLASS_NAMES_TOPIC, DEFAULT_TOPIC, GT_FIELD, SEGMENT_FIELD
from point_gn_ros.bag.errors import (BagCorruptError, BagNotFoundError, EmptyBagError,
                                     MissingTopicError, NoGroundTruthError, WrongTypeError)
from point_gn_ros.bag.realism import Realism
from point_gn_ros.bag.reader import NO_SEGMENT, read_bag
from point_gn_ros.bag.writer import WriteOptions, write_bag
from point_gn_ros.cli import main as cli_main

START_NS = 1_700_000_000_000_000_000
PC2 = 'sensor_msgs/msg/PointCloud2'


@pytest.fixture(scope='module')
def dataset() -> ArrayDataset:
    xyz, labels, names = load_modelnet_subset('test', 1)
    return ArrayDataset(xyz[:8], labels[:8], names, path='modelnet40 test subset', split='test')


def _write(ds: ArrayDataset, path: Path, **kw: object) -> Path:
    opts = WriteOptions(start_ns=START_NS, **kw)   # type: ignore[arg-type]
    return write_bag(ds, path, opts).path


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_roundtrip_single_objects(dataset: ArrayDataset, tmp_path: Path, storage: str) -> None:
    path = _write(dataset, tmp_path / 'bag', storage=storage, rate_hz=20.0, limit=6)
    bag = read_bag(path, keep_clouds=True)
    assert (bag.storage, bag.topic, bag.segmented) == (storage, DEFAULT_TOPIC, False)
    assert bag.class_names == dataset.class_names
    assert bag.custom['point_gn.class_names'].split('\n') == dataset.class_names
    assert len(bag.messages) == 6 and bag.rate_hz == pytest.approx(20.0)
    stamps = [m.stamp_ns for m in bag.messages]
    assert stamps[0] == START_NS and all(np.diff(stamps) == 50_000_000)
    for m in bag.messages:
        assert m.gt == {NO_SEGMENT: int(dataset.labels[m.index])}
        np.testing.assert_array_equal(m.clouds[NO_SEGMENT], dataset.xyz[m.index])
        assert m.log_ns == m.stamp_ns


def test_multi_object_messages_carry_segments(dataset: ArrayDataset, tmp_path: Path) -> None:
    path = _write(dataset, tmp_path / 'bag', objects_per_message=3)
    bag = read_bag(path, keep_clouds=True)
    assert bag.segmented and [len(m.gt) for m in bag.messages] == [3, 3, 2]
    last = bag.messages[-1]
    assert last.gt == {0: int(dataset.labels[6]), 1: int(dataset.labels[7])}
    # Objects of one message sit side by side, shape unchanged.
    np.testing.assert_allclose(last.clouds[1] - [2.5, 0, 0], dataset.xyz[7], atol=1e-5)


def test_realism_sensor_frame_noise_dropout_partial(dataset: ArrayDataset,
                                                    tmp_path: Path) -> None:
    realism = Realism(sensor_frame=True, noise=0.002, dropout=0.2, partial=0.5)
    bag = read_bag(_write(dataset, tmp_path / 'a', realism=realism, seed=3), keep_clouds=True)
    again = read_bag(_write(dataset, tmp_path / 'b', realism=realism, seed=3,
                            objects_per_message=2), keep_clouds=True)
    for m in bag.messages:
        xyz = m.clouds[NO_SEGMENT]
        assert 0.5 * 0.7 * 1024 < len(xyz) < 0.5 * 0.9 * 1024   # half cut, 20 % dropped
        size = np.ptp(xyz, axis=0).max()
        assert 0.1 < size < 2.0 * np.sqrt(2) + 0.05   # <= 2 m before the yaw
        assert np.linalg.norm(xyz.mean(axis=0)[:2]) > 1.5   # metres ahead of the sensor
    # Per-object seeding: grouping objects differently does not change them.
    np.testing.assert_array_equal(again.messages[0].clouds[1], bag.messages[1].clouds[-1])


def test_cli_write_and_info(tmp_path: Path, modelnet_dir: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    if not (modelnet_dir / 'ply_data_test0.h5').exists():
        pytest.skip('no ModelNet40 test split')
    out = tmp_path / 'cli_bag'
    assert cli_main(['bag', 'write', str(modelnet_dir), '-o', str(out), '--limit', '5',
                     '--storage', 'sqlite3', '--objects-per-message', '2']) == 0
    assert 'wrote' in capsys.readouterr().out
    assert cli_main(['bag', 'info', str(out)]) == 0
    text = capsys.readouterr().out
    assert '3 message(s), 5 object(s)' in text and 'segmented' in text


@pytest.mark.parametrize('args, needle', [
    (['--dropout', '1.5'], '--dropout'),
    (['--partial', '0'], '--partial'),
    (['--rate', '0'], '--rate'),
    (['--topic', 'relative'], '--topic'),
    (['--max-yaw', '200'], '--max-yaw'),
])
def test_cli_write_rejects_bad_options(args: list[str], needle: str, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(['bag', 'write', str(tmp_path), '-o', str(tmp_path / 'x'), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('point_gn: error:') and needle in err and '\n' not in err


def test_write_refuses_existing_output(dataset: ArrayDataset, tmp_path: Path) -> None:
    from point_gn_ros.bag.errors import BagError
    with pytest.raises(BagError, match='already exists'):
        _write(dataset, tmp_path)


# ------------------------------------------------------------------ bad bags


def _raw_bag(path: Path, topics: dict[str, str], messages: list[tuple[str, object]],
             storage: str = 'mcap') -> Path:
    """A bag with the given topics (name -> type) and rosbags messages, written directly."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {t: w.add_connection(t, ty, typestore=ts) for t, ty in topics.items()}
        for i, (topic, msg) in enumerate(messages):
            w.write(conns[topic], START_NS + i, ts.serialize_cdr(msg, topics[topic]))
    return path


def _cloud_without_gt() -> object:
    from rosbags.typesys import Stores, get_typestore

    from point_gn_ros.bag.writer import pack_cloud
    msg = pack_cloud(get_typestore(Stores.ROS2_JAZZY), START_NS, 'sensor',
                     np.zeros((4, 3), np.float32), np.zeros(4, np.int32), None)
    msg.fields = [f for f in msg.fields if f.name != GT_FIELD]   # still decodable: x, y, z
    return msg


def _truncate(bag: Path) -> Path:
    (file,) = [f for f in bag.iterdir() if f.suffix in ('.mcap', '.db3')]
    os.truncate(file, file.stat().st_size // 2)
    return bag


def _bad_bags(tmp: Path, ds: ArrayDataset) -> dict[str, tuple[Path, list[str], type]]:
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    string = ts.types['std_msgs/msg/String']
    (tmp / 'plain_dir').mkdir()
    return {
        'not found': (tmp / 'nope', [], BagNotFoundError),
        'not a bag': (tmp / 'plain_dir', [], BagNotFoundError),
        'missing topic': (_write(ds, tmp / 'good', limit=2), ['--topic', '/other'],
                          MissingTopicError),
        'no cloud topic': (_raw_bag(tmp / 'strings', {'/chatter': 'std_msgs/msg/String'},
                                    [('/chatter', string(data='hi'))]), [], MissingTopicError),
        'wrong type': (_raw_bag(tmp / 'wrong', {DEFAULT_TOPIC: 'std_msgs/msg/String'},
                                [(DEFAULT_TOPIC, string(data='hi'))]), [], WrongTypeError),
        'empty': (_raw_bag(tmp / 'empty', {DEFAULT_TOPIC: PC2}, []),
                  [], EmptyBagError),
        'truncated mcap': (_truncate(_write(ds, tmp / 'tm', limit=4)), [], BagCorruptError),
        'truncated sqlite3': (_truncate(_write(ds, tmp / 'ts', limit=4, storage='sqlite3')),
                              [], BagCorruptError),
        'no class names': (_raw_bag(tmp / 'nonames', {DEFAULT_TOPIC: PC2},
                                    [(DEFAULT_TOPIC, _cloud_without_gt())]), [],
                           NoGroundTruthError),
        'no gt field': (_raw_bag(tmp / 'nogt', {DEFAULT_TOPIC: PC2,
                                                CLASS_NAMES_TOPIC: 'std_msgs/msg/String'},
                                 [(CLASS_NAMES_TOPIC, string(data='a\nb')),
                                  (DEFAULT_TOPIC, _cloud_without_gt())]), [],
                        NoGroundTruthError),
    }


def test_bad_bags_one_clear_error_each(dataset: ArrayDataset, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    for what, (path, extra, error) in _bad_bags(tmp_path, dataset).items():
        with pytest.raises(error) as info:
            read_bag(path, *(extra[1:] if extra else []))
        assert str(path) in str(info.value), what
        if error is NoGroundTruthError:
            continue    # not an error for the CLI: a bag of clouds is replayed without it
        # The CLI: one line on stderr, exit code 2, for info, offline and live replay alike.
        for cmd in (['bag', 'info'], ['replay', '--offline'], ['replay', '--lockstep']):
            assert cli_main([*cmd, str(path), *extra]) == 2, (what, cmd)
            err = capsys.readouterr().err.strip()
            assert err.startswith('point_gn: error:') and '\n' not in err, (what, cmd, err)
            assert str(info.value) in err, (what, cmd)


def test_segment_field_must_be_consistent(dataset: ArrayDataset, tmp_path: Path) -> None:
    from rosbags.typesys import Stores, get_typestore

    from point_gn_ros.bag.errors import BagError
    from point_gn_ros.bag.writer import pack_cloud
    ts = get_typestore(Stores.ROS2_JAZZY)
    xyz, lab = np.zeros((4, 3), np.float32), np.zeros(4, np.int32)
    msgs = [pack_cloud(ts, START_NS + i, 's', xyz, lab, seg)
            for i, seg in enumerate((None, np.zeros(4, np.int32)))]
    path = _raw_bag(tmp_path / 'mixed', {DEFAULT_TOPIC: 'sensor_msgs/msg/PointCloud2',
                                         CLASS_NAMES_TOPIC: 'std_msgs/msg/String'},
                    [(CLASS_NAMES_TOPIC, ts.types['std_msgs/msg/String'](data='a')),
                     *[(DEFAULT_TOPIC, m) for m in msgs]])
    with pytest.raises(BagError, match=SEGMENT_FIELD):
        read_bag(path)
