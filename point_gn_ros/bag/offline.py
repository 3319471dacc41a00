"""`replay --offline`: classify the bag's objects with the core library, no ROS graph.

Mirrors what the node does with each message (same codec, same Recognizer, objects below
min_points skipped) so that the online report can be checked against it.
"""

from __future__ import annotations

import time

from point_gn_ros.bag import DEFAULT_MIN_POINTS
from point_gn_ros.bag.reader import BagContents
from point_gn_ros.bag.report import Answer, RunResult, map_class_ids

BATCH = 32   # the node's default max_batch


def run_offline(contents: BagContents, bank: str | None = None, device: str = 'cpu',
                unknown_threshold: float | None = None,
                min_points: int = DEFAULT_MIN_POINTS, progress: bool = False,
                metric_size: bool = True) -> RunResult:
    """Contents must have been read with keep_clouds=True. Answers as the node at its defaults."""
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.as_node(bank, device=device, unknown_threshold=unknown_threshold or None,
                             metric_size=metric_size)
    lut = map_class_ids(list(rec.class_names), contents.class_names)
    keys, clouds = [], []
    for m in contents.messages:
        assert m.clouds is not None, 'read_bag(..., keep_clouds=True) is needed offline'
        for seg, xyz in m.clouds.items():
            if len(xyz) >= min_points:
                keys.append((m.index, seg))
                clouds.append(xyz)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(clouds), desc='classifying', unit='object')
    answers: dict[tuple[int, int], Answer] = {}
    t0 = time.perf_counter()
    for start in range(0, len(clouds), BATCH):
        res = rec.classify_clouds(clouds[start:start + BATCH])
        for key, label, score in zip(keys[start:start + BATCH], res.labels, res.scores,
                                     strict=True):
            answers[key] = Answer(int(lut[label]) if label >= 0 else -1, float(score))
        if bar is not None:
            bar.update(len(res.labels))
    if bar is not None:
        bar.close()
    # The node answers every segmented message it can decode (even with no object left) and
    # a single-object message only when the object has min_points.
    answered = {m.index for m in contents.messages
                if contents.segmented or any((m.index, s) in answers for s in m.gt)}
    return RunResult('offline', answers, answered, len(contents.messages),
                     time.perf_counter() - t0, node=None,
                     info={'bank': str(rec.bank.path), 'min_points': min_points})
