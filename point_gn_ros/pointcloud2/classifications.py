"""The ``~/classifications`` output contract: one PointCloud2 point per classified object.

Field layout in ``classification_fields``; ``make_classifications`` builds the message,
``decode_classifications`` reads it back into plain arrays.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from point_gn_ros.errors import DecodeError
from point_gn_ros.pointcloud2.build import assemble_pointcloud2
from point_gn_ros.pointcloud2.decode import (_DATATYPE_OF, DEFAULT_MAX_POINTS, _column,
                                             _structured_view)


def classification_fields(k: int) -> list[tuple[str, np.dtype]]:
    """Field layout of a ``~/classifications`` message with top-``k`` results, in order."""
    i32, f32 = np.dtype(np.int32), np.dtype(np.float32)
    return ([('x', f32), ('y', f32), ('z', f32), ('class_id', i32), ('score', f32)]
            + [(f'topk_id_{i}', i32) for i in range(k)]
            + [(f'topk_score_{i}', f32) for i in range(k)]
            + [('segment_id', i32), ('topic_index', i32)])


@lru_cache(maxsize=16)
def _layout(k: int) -> tuple[np.dtype, tuple[tuple[str, int, int], ...], int]:
    """The packed records of classification_fields(k): (record dtype, PointField spec, step).

    The dtype holds the top-k ids and scores as one (k,) sub-array each, so that one
    assignment fills each group; the bytes are those of the k + 7 single fields.
    """
    spec, offset = [], 0
    for name, dt in classification_fields(k):
        spec.append((name, offset, _DATATYPE_OF[dt]))
        offset += dt.itemsize
    f4, i4 = '<f4', '<i4'
    rec = np.dtype({'names': ['xyz', 'class_id', 'score', 'topk_id', 'topk_score', 'segment_id',
                              'topic_index'],
                    'formats': [(f4, (3,)), i4, f4, (i4, (k,)), (f4, (k,)), i4, i4],
                    'offsets': [0, 12, 16, 20, 20 + 4 * k, 20 + 8 * k, 24 + 8 * k],
                    'itemsize': offset})
    return rec, tuple(spec), offset


def _per_object(name: str, values: Any, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """The values (of shape, or one scalar for every object) as dtype; integers must fit."""
    arr = np.asarray(values)
    if arr.ndim == 0:  # scalar: same value for every object (e.g. segment_id=-1)
        arr = np.full(shape, arr)
    if arr.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got {arr.shape}')
    if arr.dtype.kind in 'iu' and np.dtype(dtype).kind == 'i' and arr.size:
        info = np.iinfo(dtype)
        if arr.min() < info.min or arr.max() > info.max:
            raise ValueError(f'{name} values do not fit in {np.dtype(dtype)}')
    return arr.astype(dtype, copy=False)


def make_classifications(header: Any, centroids: np.ndarray, class_id: np.ndarray,
                         score: np.ndarray, topk_ids: np.ndarray, topk_scores: np.ndarray,
                         segment_id: np.ndarray | int, topic_index: np.ndarray | int, *,
                         frame_id: str | None = None) -> Any:
    """Build the ``~/classifications`` PointCloud2: one point per classified object.

    centroids (M, 3) float; class_id (M,) int (-1 = unknown); score (M,) float;
    topk_ids (M, k) int; topk_scores (M, k) float; segment_id (M,) int or scalar (-1 when the
    source message was one object); topic_index (M,) int or scalar. M may be 0.
    Fields (see classification_fields): x, y, z, class_id, score, topk_id_0..k-1,
    topk_score_0..k-1, segment_id, topic_index. Built straight into the packed records
    (one assignment a column group): it runs for every answer on the node's worker.
    """
    centroids = np.asarray(centroids)
    if centroids.ndim != 2 or centroids.shape[1] != 3:
        raise ValueError(f'centroids must have shape (M, 3), got {centroids.shape}')
    m = centroids.shape[0]
    topk_ids = np.asarray(topk_ids)
    topk_scores = np.asarray(topk_scores)
    if topk_ids.ndim != 2 or topk_ids.shape[0] != m:
        raise ValueError(f'topk_ids must have shape ({m}, k), got {topk_ids.shape}')
    if topk_scores.shape != topk_ids.shape:
        raise ValueError(f'topk_scores shape {topk_scores.shape} != topk_ids shape '
                         f'{topk_ids.shape}')
    k = topk_ids.shape[1]
    dtype, spec, point_step = _layout(k)
    rec = np.empty(m, dtype=dtype)
    rec['xyz'] = centroids
    rec['class_id'] = _per_object('class_id', class_id, (m,), np.int32)
    rec['score'] = _per_object('score', score, (m,), np.float32)
    rec['topk_id'] = _per_object('topk_ids', topk_ids, (m, k), np.int32)
    rec['topk_score'] = topk_scores
    rec['segment_id'] = _per_object('segment_id', segment_id, (m,), np.int32)
    rec['topic_index'] = _per_object('topic_index', topic_index, (m,), np.int32)
    return assemble_pointcloud2(header, rec, spec, point_step, frame_id=frame_id,
                                is_dense=bool(np.isfinite(rec['xyz']).all()))


def decode_classifications(msg: Any, *, max_points: int = DEFAULT_MAX_POINTS
                           ) -> dict[str, np.ndarray]:
    """Decode a ``~/classifications`` PointCloud2 into plain numpy arrays.

    Returns centroid (M, 3) float32, class_id (M,) int32, score (M,) float32,
    topk_ids (M, k) int32, topk_scores (M, k) float32, segment_id (M,) int32,
    topic_index (M,) int32. k is the number of consecutive topk_id_i fields. M may be 0.
    Nothing is dropped (NaN centroids are kept). Raises DecodeError if malformed.
    """
    try:
        present = {f.name for f in msg.fields}
    except (AttributeError, TypeError):
        raise DecodeError('not a PointCloud2 (bad fields)') from None
    k = 0
    while f'topk_id_{k}' in present:
        k += 1
    names = [name for name, _ in classification_fields(k)]
    view, height, width, _ = _structured_view(msg, names, max_points=max_points,
                                              allow_empty=True)
    m = height * width
    types = dict(classification_fields(k))
    col = {name: _column(view, name, types[name]) for name in names}
    return {
        'centroid': np.stack([col['x'], col['y'], col['z']], axis=1).reshape(m, 3),
        'class_id': col['class_id'],
        'score': col['score'],
        'topk_ids': np.stack([col[f'topk_id_{i}'] for i in range(k)], axis=1).reshape(m, k)
        if k else np.zeros((m, 0), np.int32),
        'topk_scores': np.stack([col[f'topk_score_{i}'] for i in range(k)],
                                axis=1).reshape(m, k)
        if k else np.zeros((m, 0), np.float32),
        'segment_id': col['segment_id'],
        'topic_index': col['topic_index'],
    }
