"""The node's ROS-free pipeline steps it relies on, and its vision_msgs answers."""

from __future__ import annotations

from dataclasses import dataclass, field
import threading
from typing import Any

import numpy as np
import pytest

from point_gn_ros.bank.classifier import Classification, unknown_rules
from point_gn_ros.node.frames import UpConvention
from point_gn_ros.node.params import PARAMETERS, settings_from_values
from point_gn_ros.node.pipeline import Answer, Job, Pipeline
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import QueueItem


@dataclass
class _Bank:
    meta: dict[str, Any] = field(default_factory=dict)
    path: str = 'fake.npz'


@dataclass
class _Classifier:
    unknown_threshold: float | None = None


class _FakeRecognizer:
    """Labels each cloud by the sign of its mean z: 0 = up (z > 0), 1 = down; records input."""

    def __init__(self, names: list[str]) -> None:
        self.class_names, self.bank, self.classifier = names, _Bank(), _Classifier()
        self.top_k, self.seen = 5, []

    def set_unknown_threshold(self, value: float | None) -> None:
        """As Recognizer's: the classifier resolves it (bank/classifier.py unknown_rules)."""
        self.classifier.unknown_threshold = unknown_rules(self.bank, value).probability

    def classify_clouds(self, clouds: list[np.ndarray]) -> Classification:
        self.seen += [c.copy() for c in clouds]
        k = min(self.top_k, len(self.class_names))
        labels = np.array([0 if c[:, 2].mean() > 0 else 1 for c in clouds], np.int64)
        scores = np.full(len(clouds), 0.9, np.float32)
        topk = np.stack([labels, 1 - labels] + [labels] * (k - 2), axis=1)[:, :k]
        return Classification(labels, scores, topk, np.full(topk.shape, 0.5, np.float32))


@dataclass
class _Header:
    frame_id: str


@dataclass
class _Msg:
    header: _Header
    xyz: np.ndarray


def _pipeline(rec: _FakeRecognizer) -> Pipeline:
    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    settings = settings_from_values(values | {'min_points': 1})
    return Pipeline(rec, settings, NodeStats(1), lambda key, text: True, threading.Event())


def _job(xyz: np.ndarray, frame: str, pipe: Pipeline) -> Job:
    item = QueueItem(0, _Msg(_Header(frame), xyz), 0.0, 0)
    return Job(item, [-1], [xyz], pipe.frame_rotation(frame))


def test_classifier_sees_z_up_outputs_keep_the_input_frame() -> None:
    rec = _FakeRecognizer(['up', 'down'])
    pipe = _pipeline(rec)
    pipe.frame_rotation = UpConvention('auto')
    # An object above the camera centre in optical axes: y is down, so y < 0 is up.
    optical = np.array([[0.0, -1.0, -2.0], [0.1, -1.2, -2.0]], np.float32)
    jobs = [_job(optical, 'cam_optical_frame', pipe), _job(optical, 'base_link', pipe)]
    results = pipe.classify([c for j in jobs for c in j.model_clouds()])
    answers = pipe.answers(jobs, results)
    assert [int(a.labels[0]) for a in answers] == [0, 1]        # turned vs taken as z-up
    assert answers[0].job.clouds[0] is optical                  # outputs: input frame
    np.testing.assert_allclose(answers[0].centroids[0], optical.mean(axis=0), atol=1e-6)
    np.testing.assert_allclose(rec.seen[0][:, 2], -optical[:, 1])


def test_update_applies_between_batches() -> None:
    import dataclasses

    rec, other = _FakeRecognizer(['up', 'down']), _FakeRecognizer(['a', 'b', 'c'])
    pipe = _pipeline(rec)
    pipe.update(dataclasses.replace(pipe.settings, top_k=2, unknown_threshold=0.4), other)
    assert pipe.recognizer is rec and pipe.settings.top_k == 5    # not in the middle of one
    out: list[Answer] = []
    from point_gn_ros.pointcloud2 import xyz_to_pointcloud2
    from std_msgs.msg import Header
    item = QueueItem(0, xyz_to_pointcloud2(Header(frame_id='base_link'),
                                           np.ones((3, 3), np.float32)), 0.0, 0)
    pipe.process([item], out.append)
    assert pipe.recognizer is other and other.top_k == 2
    assert other.classifier.unknown_threshold == pytest.approx(0.4)
    assert out[0].topk_ids.shape == (1, 2) and pipe.class_names == ['a', 'b', 'c']


def test_detections_carry_boxes_names_scores_and_unknown() -> None:
    from node_testing import require_ros_extras
    require_ros_extras('vision_msgs.msg')
    from std_msgs.msg import Header

    from point_gn_ros.node.outputs import make_detections, make_label_info

    clouds = [np.array([[0, 0, 0], [1, 2, 3]], np.float32),
              np.array([[-1, -1, -1], [-2, 0, 1]], np.float32)]
    item = QueueItem(0, None, 0.0, 0)
    answer = Answer(Job(item, [4, 9], clouds), np.array([1, -1]), np.array([0.8, 0.2]),
                    np.array([[1, 0], [0, 1]]), np.array([[0.8, 0.1], [0.2, 0.1]]))
    arr = make_detections(Header(frame_id='f'), answer, ['cup', 'mug'])
    assert arr.header.frame_id == 'f' and [d.id for d in arr.detections] == ['4', '9']
    first, second = arr.detections
    assert (first.bbox.center.position.x, first.bbox.size.z) == (0.5, 3.0)
    assert [(r.hypothesis.class_id, r.hypothesis.score) for r in first.results] == [
        ('mug', pytest.approx(0.8)), ('cup', pytest.approx(0.1))]
    assert [r.hypothesis.class_id for r in second.results] == ['unknown', 'cup', 'mug']
    assert second.results[0].pose.pose.position.x == pytest.approx(-1.5)
    info = make_label_info(['cup', 'mug'], None, Header().stamp)
    assert [(c.class_id, c.class_name) for c in info.class_map] == [(0, 'cup'), (1, 'mug')]
    assert info.threshold == 0.0
