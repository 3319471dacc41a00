"""The node's worker path without DDS: per-message wall and CPU time, and `prepare` per cloud.

Feeds the node's `Pipeline` (default parameters, shipped default bank) real PointCloud2
messages of the demo objects in their sensor frames, in micro-batches of --batch, and builds
the `~/classifications` message of every answer, as the node does; then times `prepare`
(the node's resampling, midpoint fill and yaw alignment) on the same objects whole and as
single-view scans. With --rate, messages come at that rate instead of back to back, as a
sensor's do: the CPUs idle in between, and the per-message wall times are given as p50 / p90 /
p99. For A/B runs of two trees, interleaved (from a directory outside both, so that the
tree on PYTHONPATH is the one imported):

Run: PYTHONPATH=TREE python benchmarks/node_path_time.py [--messages 200] [--batch 1] [--rate HZ]
     [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import threading
import time
import timeit
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
from point_gn_ros.core.sampling import prepare
from point_gn_ros.node.frames import UpConvention
from point_gn_ros.node.params import PARAMETERS, settings_from_values
from point_gn_ros.node.pipeline import Answer, Pipeline
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import QueueItem
from point_gn_ros.pointcloud2 import make_classifications, xyz_to_pointcloud2
from point_gn_ros.recognizer import Recognizer, make_encoder


def worker_pipeline(overrides: dict[str, Any], stop: threading.Event
                    ) -> tuple[Any, FeatureBank, Pipeline]:
    """The node's worker pipeline on the shipped bank -> (settings, bank, pipeline).

    Default parameters updated by overrides, one input topic, the recognizer warmed up.
    """
    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    s = settings_from_values(values | overrides | {'input_topics': ['objects']})
    torch.set_num_threads(s.torch_threads)
    bank = FeatureBank.load(None)
    rec = Recognizer(bank, 'cpu', s.resample, s.top_k, s.unknown_threshold or None,
                     encoder=make_encoder(bank.config, 'cpu', threads=s.encoder_threads),
                     search=s.search)
    rec.warmup()
    pipe = Pipeline(rec, s, NodeStats(1), lambda key, text: True, stop)
    pipe.frame_rotation = UpConvention(s.up_axis)
    return s, bank, pipe


def classifications_of(a: Answer) -> Any:
    """The answer's ~/classifications message, built as the node builds it."""
    return make_classifications(a.job.item.payload.header, a.centroids, a.labels, a.scores,
                                a.topk_ids, a.topk_scores,
                                np.asarray(a.job.segment_ids, dtype=np.int64), 0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--messages', type=int, default=200)
    p.add_argument('--batch', type=int, default=1)
    p.add_argument('--rate', type=float, default=0.0,
                   help='messages per second (0: back to back)')
    p.add_argument('--profile', action='store_true', help='cProfile one more pass')
    p.add_argument('--sort', default='tottime', help='cProfile sort key (tottime, cumulative)')
    args = p.parse_args()
    from std_msgs.msg import Header

    s, bank, pipe = worker_pipeline({}, threading.Event())
    objects = load_demo_objects()
    rng = np.random.default_rng(0)
    whole = [place_in_sensor_frame(x, rng) for x in objects.xyz]
    scans = [place_in_sensor_frame(x, rng, single_view=True) for x in objects.xyz]
    msgs = [xyz_to_pointcloud2(Header(frame_id='sensor'), x) for x in whole]
    publish = classifications_of

    def run(n: int) -> list[float]:
        """Process n messages in batches -> each batch's wall time (s), paced by --rate."""
        times, next_t = [], time.perf_counter()
        for i in range(0, n, args.batch):
            if args.rate > 0:
                next_t += args.batch / args.rate
                time.sleep(max(0.0, next_t - time.perf_counter()))
            t = time.perf_counter()
            pipe.process([QueueItem(0, msgs[(i + j) % len(msgs)], 0.0, 0)
                          for j in range(args.batch)], publish)
            times.append(time.perf_counter() - t)
        return times

    run(20)
    for _ in range(3):
        t, c = time.perf_counter(), time.process_time()
        times = run(args.messages)
        if args.rate > 0:   # the idle time between messages is not the path's
            p50, p90, p99 = np.percentile(times, [50, 90, 99]) * 1e3
            cpu_ms = (time.process_time() - c) / args.messages * 1e3
            print(f'batch {args.batch} at {args.rate:g}/s: p50 {p50:.2f}, p90 {p90:.2f}, p99 '
                  f'{p99:.2f} ms wall per batch, {cpu_ms:.2f} ms CPU per message')
            continue
        print(f'batch {args.batch}: {(time.perf_counter() - t) / args.messages * 1e3:.2f} ms '
              f'wall, {(time.process_time() - c) / args.messages * 1e3:.2f} ms CPU per message')
    for name, clouds in (('complete', whole), ('scan', scans)):
        def prep(cl: list[np.ndarray] = clouds) -> None:
            for c in cl:
                prepare(c, s.num_points, s.resample, yaw_align=bank.config.yaw_align,
                        upsample=bank.config.upsample)
        t = min(timeit.repeat(prep, number=3, repeat=7)) / 3 / len(clouds)
        print(f'prepare, {name} objects: {t * 1e3:.3f} ms per cloud (min of 7)')
    if args.profile:
        prof = cProfile.Profile()
        prof.enable()
        run(args.messages)
        prof.disable()
        pstats.Stats(prof).sort_stats(args.sort).print_stats(40)


if __name__ == '__main__':
    main()
