"""Worst-case service time of one message under the node's limits (ROS-free, default bank).

Runs the node's Pipeline (decode, split, resample, encode, classify, build the answer) on
single messages at the limits: max_points_per_message points as one object, the same points
as max_objects_per_message segments, the campaign's 2,000 segments of 16 points (truncated
to the limit), and a message over the point limit (rejected unread). Each case is timed
`--repeats` times; the minimum and maximum are reported (the maximum is the bound on this
machine; on a shared machine the minimum shows how much of it is other people's load).

    python benchmarks/service_time_bound.py [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np

from point_gn_ros.clients.fuzz_messages import fuzz_header, pack_cloud
from point_gn_ros.node.params import PARAMETERS, settings_from_values
from point_gn_ros.node.pipeline import Pipeline
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import QueueItem


def _message(points: int, segments: int, rng: np.random.Generator) -> object:
    xyz = rng.normal(size=(points, 3)).astype(np.float32)
    seg = (np.arange(points) % segments).astype(np.int32)
    return pack_cloud(fuzz_header(0), [('x', xyz[:, 0]), ('y', xyz[:, 1]), ('z', xyz[:, 2]),
                                       ('segment', seg)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--threads', type=int, default=2)
    ap.add_argument('--repeats', type=int, default=3)
    args = ap.parse_args()

    import torch

    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.recognizer import Recognizer, make_encoder

    torch.set_num_threads(1)   # the node default: the classifier on one torch thread
    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    values.update(segment_field='segment', torch_threads=1, encoder_threads=args.threads)
    s = settings_from_values(values)
    bank = FeatureBank.load(None)
    rec = Recognizer(bank, 'cpu', s.resample, s.top_k, None,
                     encoder=make_encoder(bank.config, 'cpu', threads=args.threads))
    rec.warmup()
    stats = NodeStats(1)
    pipe = Pipeline(rec, s, stats, lambda key, text: None, threading.Event())
    rng = np.random.default_rng(0)
    p, o = s.max_points_per_message, s.max_objects_per_message
    cases = {
        f'{p:,} points, 1 object': _message(p, 1, rng),
        f'{p:,} points, {o} objects': _message(p, o, rng),
        f'{p:,} points, 2,000 segments (truncated to {o})': _message(p, 2000, rng),
        f'32,000 points, 2,000 segments of 16 (truncated to {o})': _message(32_000, 2000, rng),
        f'{p + 1:,} points (over the limit: rejected)': _message(p + 1, 1, rng),
    }
    print(f'limits: max_points_per_message={p:,} max_objects_per_message={o} '
          f'max_batch={s.max_batch}; default bank {bank.config.to_dict()}; '
          f'{args.threads} thread(s)')
    for name, msg in cases.items():
        times = []
        for _ in range(args.repeats):
            stats.on_received(0)
            t = time.perf_counter()
            objects: list[int] = []

            def publish(answer: object, objects: list[int] = objects) -> None:
                objects.append(len(answer.labels))   # what the node publishes, counted
                stats.on_published(0, len(answer.labels), 0.0, None)

            pipe.process([QueueItem(0, msg, time.monotonic(), 0)], publish)
            times.append(time.perf_counter() - t)
        print(f'{name:58s} min {min(times) * 1e3:7.1f} ms  max {max(times) * 1e3:7.1f} ms  '
              f'objects {objects or "rejected"}', flush=True)
    snap = stats.snapshot([0])
    print(f'answered {snap.answered}, rejected {dict(snap.rejected)}, '
          f'objects truncated {snap.objects_truncated}, identity {snap.unaccounted()} off')


if __name__ == '__main__':
    main()
