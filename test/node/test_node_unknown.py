"""The node's default unknown rules over real DDS: what is no object comes out unknown.

Random Gaussian blobs (the volume rule, core/surface.py), a whole scene (two chairs on a
floor: the scene rule, core/surface.py) and a garbage decode (byte-swapped floats: sizes no
class has, bank/taught.py's fit rule) get class_id -1 at the node's default parameters; a real
object's single-view scan at a plausible size keeps its class.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from node_testing import (BANK_CLASSES, NODE_FQN, TEST_NUM_POINTS, Harness, NodeProcess,
                          cloud_msg, harness, pick, reliable_qos, stamp, stamp_key, tiny_bank)

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

TOPIC = 'objects'
ANSWER_TIMEOUT_S = 60.0


@pytest.fixture(scope='module')
def node(tiny_bank: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[NodeProcess]:
    proc = NodeProcess({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': [TOPIC], 'queue_size': 16, 'qos_depth': 20},
                       tmp_path_factory.mktemp('node') / 'node.log')
    try:
        yield proc
    finally:
        proc.stop()


def _clouds() -> tuple[list[np.ndarray], list[str]]:
    from point_gn_ros.bank.taught import plausible_scale
    from point_gn_ros.core.views import simulate_view

    rng = np.random.default_rng(5)
    blobs = [(rng.normal(size=(50, 3)) * sd + [4.0, 0.0, 1.0]).astype(np.float32)
             for sd in (0.05, 0.2, 1.0)]
    garbage = rng.normal(size=(600, 3)).astype('>f4').view('<f4').astype(np.float32)
    garbage = garbage[np.isfinite(garbage).all(1)]
    views = []
    for name, obj in zip(('bottle', 'chair', 'chair'), [*pick('test', ('bottle',), 1)[0],
                                                         *pick('test', ('chair',), 2)[0]],
                         strict=True):
        view = simulate_view(obj, 3).points * plausible_scale(obj, name)
        views.append((view - [*view[:, :2].mean(0), view[:, 2].min()]).astype(np.float32))
    # two chairs 1.5 m apart on a 4 x 3 m floor
    floor = np.c_[(rng.random((3000, 2)) - 0.5) * [4.0, 3.0], rng.normal(0, 0.005, 3000)]
    scene = np.concatenate([floor, views[1] + [-1.0, 0.0, 0.0], views[2] + [1.0, 0.0, 0.0]])
    real = [v + [3.0, 1.0, 0.0] for v in views[:2]]
    return [*blobs, garbage, scene.astype(np.float32), *real], \
        ['blob'] * 3 + ['garbage', 'scene', 'bottle', 'chair']


def test_blobs_scenes_and_garbage_are_unknown_and_real_objects_are_not(
        harness: Harness, node: NodeProcess, tiny_bank: Path) -> None:
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.pointcloud2 import decode_classifications

    pub = harness.node.create_publisher(PointCloud2, TOPIC, reliable_qos(20))
    answers = harness.collect(PointCloud2, f'{NODE_FQN}/classifications', reliable_qos(50))
    harness.wait_for_subscribers([pub], node)
    harness.spin_for(0.5)
    clouds, kinds = _clouds()
    keys = [(9000 + i, 0) for i in range(len(clouds))]
    for cloud, key in zip(clouds, keys, strict=True):
        pub.publish(cloud_msg(cloud, 'base_link', stamp(*key)))

    def got(key: tuple[int, int]) -> list:
        return [m for m in answers if stamp_key(m.header) == key]
    assert harness.spin_until(lambda: all(got(k) for k in keys), ANSWER_TIMEOUT_S), node.log()
    ids = [int(decode_classifications(got(k)[0])['class_id'][0]) for k in keys]
    for kind, cid in zip(kinds, ids, strict=True):
        if kind in ('blob', 'garbage', 'scene'):
            assert cid == -1, f'{kind}: class {cid}, expected unknown'
        else:
            assert cid >= 0 and BANK_CLASSES[cid] == kind, f'{kind} answered {cid}'
