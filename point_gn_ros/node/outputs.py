"""The node's answers as ROS messages, and the publishers that send them.

Message builders for vision_msgs (Detection3DArray, LabelInfo) and `Outputs`, the set of
lifecycle publishers. `vision_msgs` comes with every ROS distribution but has no pip wheel;
where it cannot be imported the node keeps its PointCloud2 output only and says so once.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from point_gn_ros.node.markers import MarkerTracker, object_box
from point_gn_ros.node.pipeline import Answer

UNKNOWN_NAME = 'unknown'


def vision_msgs_available() -> bool:
    """Whether vision_msgs' Python messages can be imported here."""
    try:
        import vision_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


def class_name(class_names: Sequence[str], class_id: int) -> str:
    return class_names[class_id] if 0 <= class_id < len(class_names) else UNKNOWN_NAME


def make_detections(header: Any, answer: Answer, class_names: Sequence[str]) -> Any:
    """vision_msgs/Detection3DArray for one answered message (input header and frame).

    Per object: `bbox` the axis-aligned box of its points in the input frame (identity
    orientation); `results` the top-k hypotheses (class_id = class name, score), each with
    the object's centroid as pose; an object labelled unknown gets a first hypothesis
    'unknown' with its top-1 score; `id` = its segment id ('-1' = the whole message).
    """
    from vision_msgs.msg import Detection3D, Detection3DArray, ObjectHypothesisWithPose

    out = Detection3DArray(header=header)
    centroids = answer.centroids
    for i, cloud in enumerate(answer.job.clouds):
        det = Detection3D(header=header, id=str(answer.job.segment_ids[i]))
        lo, hi = cloud.min(axis=0).astype(np.float64), cloud.max(axis=0).astype(np.float64)
        centre, size = (lo + hi) / 2, hi - lo
        det.bbox.center.position.x, det.bbox.center.position.y, det.bbox.center.position.z = (
            float(v) for v in centre)
        det.bbox.center.orientation.w = 1.0
        det.bbox.size.x, det.bbox.size.y, det.bbox.size.z = (float(v) for v in size)
        hypotheses = [(int(c), float(s)) for c, s in
                      zip(answer.topk_ids[i], answer.topk_scores[i], strict=True)]
        if int(answer.labels[i]) < 0:
            hypotheses.insert(0, (-1, float(answer.scores[i])))
        for cid, score in hypotheses:
            hyp = ObjectHypothesisWithPose()
            hyp.hypothesis.class_id = class_name(class_names, cid)
            hyp.hypothesis.score = score
            hyp.pose.pose.position.x, hyp.pose.pose.position.y, hyp.pose.pose.position.z = (
                float(v) for v in centroids[i])
            hyp.pose.pose.orientation.w = 1.0
            det.results.append(hyp)
        out.detections.append(det)
    return out


def make_label_info(class_names: Sequence[str], threshold: float | None, stamp: Any) -> Any:
    """vision_msgs/LabelInfo: class_map id -> name, threshold (0 = no open-set threshold)."""
    from vision_msgs.msg import LabelInfo, VisionClass

    info = LabelInfo(threshold=float(threshold or 0.0))
    info.header.stamp = stamp
    info.class_map = [VisionClass(class_id=i, class_name=n) for i, n in enumerate(class_names)]
    return info


class Outputs:
    """The node's answer publishers (lifecycle publishers: they publish only while active).

    Created on configure, destroyed on cleanup: `~/classifications`, `~/markers`,
    `~/class_names` (latched) and, with vision_msgs, `~/detections` and `~/label_info`
    (latched). `publish()` runs on the worker thread.
    """

    def __init__(self, node: Any, input_topics: Sequence[str], qos_depth: int,
                 with_vision_msgs: bool) -> None:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String
        from visualization_msgs.msg import MarkerArray

        self._node = node
        out_qos = QoSProfile(depth=max(10, qos_depth), reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        make = node.create_lifecycle_publisher
        self.classifications = make(PointCloud2, '~/classifications', out_qos)
        self.markers = make(MarkerArray, '~/markers', out_qos)
        self.class_names = make(String, '~/class_names', latched)
        self.detections = self.label_info = None
        if with_vision_msgs:
            from vision_msgs.msg import Detection3DArray, LabelInfo
            self.detections = make(Detection3DArray, '~/detections', out_qos)
            self.label_info = make(LabelInfo, '~/label_info', latched)
        self._tracker = MarkerTracker(input_topics)

    def topic_names(self) -> list[str]:
        pubs = [self.detections, self.classifications, self.markers]
        return [p.topic_name for p in pubs if p is not None]

    def publish(self, answer: Answer, class_names: Sequence[str], marker_lifetime_s: float
                ) -> None:
        """One message's answer on every output (detections and markers only if watched)."""
        from point_gn_ros.pointcloud2 import make_classifications
        job = answer.job
        header = job.item.payload.header
        ti = job.item.topic_index
        self.classifications.publish(make_classifications(
            header, answer.centroids, answer.labels, answer.scores, answer.topk_ids,
            answer.topk_scores, np.asarray(job.segment_ids, dtype=np.int64), ti))
        if self.detections is not None and self.detections.get_subscription_count():
            self.detections.publish(make_detections(header, answer, class_names))
        if self.markers.get_subscription_count():   # nobody watching: skip the work
            boxes = [object_box(c, class_name(class_names, int(lbl)), int(lbl), float(sc))
                     for c, lbl, sc in zip(job.clouds, answer.labels, answer.scores,
                                           strict=True)]
            self.markers.publish(self._tracker.build(ti, header, boxes, marker_lifetime_s))

    def publish_labels(self, class_names: Sequence[str], threshold: float | None,
                       stamp: Any) -> None:
        """The latched class list: ~/class_names and ~/label_info."""
        from std_msgs.msg import String
        self.class_names.publish(String(data='\n'.join(class_names)))
        if self.label_info is not None:
            self.label_info.publish(make_label_info(class_names, threshold, stamp))

    def destroy(self) -> None:
        for pub in (self.classifications, self.markers, self.class_names, self.detections,
                    self.label_info):
            if pub is not None:
                self._node.destroy_lifecycle_publisher(pub)
