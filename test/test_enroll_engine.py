"""The node's enrollment engine without ROS: producers, the worker's steps, the committer."""

from __future__ import annotations

from pathlib import Path
import threading
import time

import numpy as np
import torch

from point_gn_ros.bank.enroll import BankFile, class_counts
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import simulate_views
from point_gn_ros.node.enroll_engine import EnrollEngine

D = EncoderConfig().feature_dim


class _FakeRecognizer:
    """encode(clouds) -> (B, D): a feature made from each cloud's first coordinates."""

    def __init__(self) -> None:
        self.calls: list[int] = []

    def encode(self, clouds: list[np.ndarray], augment: str = 'none') -> torch.Tensor:
        assert augment == 'none'
        self.calls.append(len(clouds))
        out = torch.zeros(len(clouds), D)
        for i, c in enumerate(clouds):
            out[i, :3] = torch.from_numpy(c[0].astype(np.float32))
            out[i, 3:] = float(c[0, 0])
        return out

    def sizes(self, clouds: list[np.ndarray]) -> None:
        return None                               # no metric size (test_size.py has one)


def _engine(tmp_path: Path, chunk: int = 4, fuse_views: bool = False, warn=None  # noqa: ANN001
            ) -> tuple[EnrollEngine, LiveBank, list]:
    g = torch.Generator().manual_seed(0)
    raw = torch.randn(12, D, generator=g)
    tf = FeatureTransform.fit(raw, 'none')
    bank = FeatureBank(features=tf(raw), labels=torch.arange(12) % 3,
                       class_names=['a', 'b', 'c'], config=EncoderConfig(), transform=tf,
                       gamma=10.0)
    live = LiveBank(BankFile.of(bank, 'float32'), lambda active: active.num_classes)
    changes: list = []
    eng = EnrollEngine(live, lambda snap, res: changes.append((snap.version, res.count)),
                       log=lambda text: None, warn=warn or (lambda key, text: None),
                       chunk=chunk, max_pending=100, capture_max=5, min_points=4,
                       fuse_views=fuse_views)
    return eng, live, changes


def _cloud(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(50, 3)).astype(np.float32)


def _drain(eng: EnrollEngine, rec: _FakeRecognizer, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while eng.step(rec) and time.monotonic() < end:
        pass
    eng.flush(timeout)


def test_streamed_examples_coalesce_into_one_version(tmp_path: Path) -> None:
    eng, live, changes = _engine(tmp_path)
    rec = _FakeRecognizer()
    for i in range(10):                           # one example per message, same class
        assert eng.submit('mug', [_cloud(i)], '~/enroll_cloud')[0]
    assert eng.pending() == 10
    _drain(eng, rec)
    assert max(rec.calls) <= 4                    # never more than a chunk per worker step
    assert changes == [(1, 10)] and class_counts(live.current().bank)['mug'] == 10
    assert eng.counters['enrolled'] == 10 and eng.pending() == 0
    eng.close()


def test_guard_rails_and_capture(tmp_path: Path) -> None:
    eng, live, changes = _engine(tmp_path)
    rec = _FakeRecognizer()
    ok, why = eng.submit('mug', [_cloud(0)[:2]], 'x')          # 2 points < min_points
    assert not ok and eng.counters['refused'] == 1
    assert not eng.submit('mug', [_cloud(0)] * 101, 'x')[0]     # over max_pending
    assert not eng.submit(' ', [_cloud(0)], 'x')[0]
    assert eng.stop_capture() == (False, 'not capturing')
    assert eng.start_capture('cup', frozenset({1}))[0]
    eng.observe(0, [_cloud(1)])                                  # another topic: ignored
    eng.observe(1, [_cloud(i) for i in range(2, 9)])             # 7 objects, cap 5
    ok, why = eng.stop_capture()
    assert ok, why
    _drain(eng, rec)
    assert class_counts(live.current().bank)['cup'] == 5
    assert 'capture of 5 object(s), 2 more over capture_max' in \
        live.current().bank.meta['enrollments'][-1]['source']
    ok, text = eng.forget('cup', 'test')
    assert ok and 'cup' not in live.current().class_names
    assert eng.forget('cup', 'test')[0] is False
    assert eng.save('')[0] is False
    ok, text = eng.save(str(tmp_path / 'saved.npz'))
    assert ok and BankFile.load(tmp_path / 'saved.npz').bank.meta['bank_version'] == 2
    eng.close()


def test_producers_worker_and_services_race(tmp_path: Path) -> None:
    """Producers on two threads, the worker stepping, forget and save in between."""
    eng, live, changes = _engine(tmp_path, chunk=3)
    rec = _FakeRecognizer()
    stop = threading.Event()

    def worker() -> None:
        while not stop.is_set():
            if not eng.step(rec):
                time.sleep(0.001)

    def producer(name: str) -> None:
        for i in range(30):
            eng.submit(name, [_cloud(i)], f'src {name}')
            time.sleep(0.0005)

    threads = [threading.Thread(target=worker)] + [
        threading.Thread(target=producer, args=(n,)) for n in ('p', 'q')]
    for t in threads:
        t.start()
    for t in threads[1:]:
        t.join()
    assert eng.save(str(tmp_path / 'mid.npz'))[0]
    end = time.monotonic() + 10
    while eng.pending() and time.monotonic() < end:
        time.sleep(0.01)
    stop.set()
    threads[0].join()
    eng.flush(10)
    counts = class_counts(live.current().bank)
    assert counts['p'] == 30 and counts['q'] == 30
    assert eng.counters['enrolled'] == 60
    versions = [v for v, _ in changes]
    assert versions == sorted(versions) and versions[-1] == live.current().version
    BankFile.load(tmp_path / 'mid.npz')                       # whole, whatever it caught
    eng.close()


def test_a_fused_capture_adds_the_union_and_its_scans(tmp_path: Path) -> None:
    """fuse_views: a capture of views of one object gains 1 + 8 examples; a moving frame none."""
    warnings: list[str] = []
    eng, live, changes = _engine(tmp_path, fuse_views=True,
                                 warn=lambda key, text: warnings.append(text))
    rec = _FakeRecognizer()
    obj = _cloud(0) * 0.3 + np.float32([2.0, 1.0, 0.0])     # one object, fixed frame
    views = [v.points for v in simulate_views(obj, 5, seed=4)]
    assert eng.start_capture('mug', None)[0]
    eng.observe(0, views)
    assert eng.stop_capture()[0]
    assert eng.submit('mug', [_cloud(9)], '~/enroll_cloud')[0]   # streamed: never fused
    _drain(eng, rec)
    assert class_counts(live.current().bank)['mug'] == 5 + 9 + 1
    assert sum(rec.calls) == 15 and max(rec.calls) <= 4          # still chunked
    log = live.current().bank.meta['enrollments']
    assert '5 views fused into 9 more examples' in log[-2]['source']
    assert eng.counters['fused'] == 1 and eng.counters['enrolled'] == 15
    assert not any('not fused' in w for w in warnings)   # (the fake features repeat)
    assert eng.pending() == 0
    # Views of a moving frame (the object elsewhere in each): enrolled as they are, warned.
    assert eng.start_capture('cup', None)[0]
    eng.observe(0, [v + np.float32([5.0 * i, 0, 0]) for i, v in enumerate(views)])
    assert eng.stop_capture()[0]
    _drain(eng, rec)
    assert class_counts(live.current().bank)['cup'] == 5
    assert eng.counters['not_fused'] == 1 and any('do not overlap' in w for w in warnings)
    assert eng.pending() == 0
    eng.close()
