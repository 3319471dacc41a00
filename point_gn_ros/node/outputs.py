"""Standard ROS messages for the node's answers: vision_msgs when installed.

`vision_msgs` (Detection3DArray, LabelInfo) comes with every ROS distribution but has no
pip wheel; where it cannot be imported the node keeps its PointCloud2 output only and
says so once at start.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

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
