"""Up-axis conventions (node/frames.py) and the live-resizable work queue: ROS-free."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.node.frames import UP_AXES, UpConvention, to_z_up, up_rotation
from point_gn_ros.node.work_queue import WorkQueue

AXIS = {'x': (1, 0, 0), 'y': (0, 1, 0), 'z': (0, 0, 1)}


@pytest.mark.parametrize('up', [a for a in UP_AXES if a != 'auto'])
def test_rotations_are_proper_and_take_up_to_z(up: str) -> None:
    r = up_rotation(up)
    r = np.eye(3) if r is None else r
    assert np.allclose(r @ r.T, np.eye(3)) and np.isclose(np.linalg.det(r), 1.0)
    vec = np.array(AXIS[up[-1]], float) * (-1 if up.startswith('-') else 1)
    assert np.allclose(r @ vec, (0, 0, 1))


def test_optical_frame_is_rep103() -> None:
    # Optical: x right, y down, z forward -> body: x forward, y left, z up.
    right, down, forward = np.eye(3, dtype=np.float32)
    r = UpConvention('auto')('camera_depth_optical_frame')
    assert np.allclose(to_z_up(forward[None], r), [[1, 0, 0]])
    assert np.allclose(to_z_up(right[None], r), [[0, -1, 0]])
    assert np.allclose(to_z_up(down[None], r), [[0, 0, -1]])
    assert UpConvention('auto')('base_link') is None
    assert UpConvention('z')('camera_optical_frame') is None          # explicit override
    assert UpConvention('-y')('lidar') is not None
    with pytest.raises(ValueError, match='up_axis'):
        UpConvention('up')


def test_optical_roundtrip_is_exact() -> None:
    rng = np.random.default_rng(0)
    z_up = rng.normal(size=(100, 3)).astype(np.float32)
    optical = np.stack([-z_up[:, 1], -z_up[:, 2], z_up[:, 0]], axis=1)   # how a camera sees it
    back = to_z_up(optical, UpConvention()('cam_optical_frame'))
    assert back.dtype == np.float32 and np.array_equal(back, z_up)


def test_queue_resize_shrinks_as_it_drains_without_dropping() -> None:
    q: WorkQueue[int] = WorkQueue(2, 5)
    for i in range(5):
        q.put(0, i)
    q.put(1, 10)
    q.resize(2)
    assert q.maxlen == 2 and q.depths() == [5, 1] and q.dropped() == [0, 0]
    assert q.put(0, 5)                                  # full: one oldest out, one in
    assert q.depths() == [5, 1] and q.dropped() == [1, 0]
    assert [it.payload for it in q.take(4) if it.topic_index == 0] == [1, 2, 3]
    assert q.depths() == [2, 0]                         # drained to the new bound ...
    assert q.put(0, 6) and q.depths() == [2, 0]         # ... and held there
    assert not q.put(1, 11)
    with pytest.raises(ValueError):
        q.resize(0)
