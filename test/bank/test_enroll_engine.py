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
from point_gn_ros.bank.model import FeatureTransform
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
        live.current().bank.enrollments[-1].source
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
    log = [e.to_json() for e in live.current().bank.enrollments]
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


def test_names_the_bank_could_not_load_are_refused_with_a_counted_reason(tmp_path: Path
                                                                       ) -> None:
    eng, live, changes = _engine(tmp_path)
    for name in ('chair\rtable', 'x' * 10_000, 'a\nb'):
        ok, why = eng.submit(name, [_cloud(0)], '~/enroll_cloud')
        assert not ok and 'single lines' in why and len(why) < 300
    assert eng.refused_by == {'class_name': 3} and eng.counters['refused'] == 3
    assert eng.pending() == 0
    eng.close()


def test_caps_on_classes_examples_and_pending_are_counted(tmp_path: Path) -> None:
    eng, live, changes = _engine(tmp_path)          # 3 classes, max_pending 100
    eng.max_classes, eng.max_examples = 5, 10
    rec = _FakeRecognizer()
    assert eng.submit('d', [_cloud(i) for i in range(15)], 'x')[0]      # 5 over the call cap
    assert eng.submit('e', [_cloud(1)], 'x')[0]
    assert not eng.submit('f', [_cloud(2)], 'x')[0]                      # a 6th class
    assert eng.submit('a', [_cloud(3)], 'x')[0]                          # an existing one
    assert eng.refused_by == {'per_call': 5, 'class_limit': 1}
    assert eng.pending() == 12
    for i in range(9):                                # 12 + 9 * 10 = 102 > 100: one refused
        eng.submit('e', [_cloud(j) for j in range(10)], f'y{i}')
    assert eng.refused_by['queue_full'] == 10 and eng.pending() == 92
    # Encoded but not committed still counts as pending (the committer is held up here).
    hold = threading.Event()
    real_add = live.add
    live.add = lambda *a, **k: (hold.wait(10), real_add(*a, **k))[1]
    while eng.step(rec):
        pass
    assert eng.pending() == 92
    hold.set()
    eng.flush(10)
    assert eng.pending() == 0 and eng.counters['enrolled'] == 92
    assert eng.counters['enrolled'] + eng.counters['refused'] == 15 + 1 + 1 + 1 + 90
    eng.close()


def test_close_drops_pending_work_at_once_and_publishes_nothing_after(tmp_path: Path) -> None:
    """600 examples waiting, a commit in progress: close() returns within 2 s, one log line."""
    logs: list[str] = []
    eng, live, changes = _engine(tmp_path)
    eng.set_log(logs.append)
    eng.max_pending = eng.max_examples = 1000
    rec = _FakeRecognizer()
    started, release = threading.Event(), threading.Event()
    real_add = live.add

    def slow_add(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - a long refit
        started.set()
        release.wait(30)
        return real_add(*args, **kwargs)
    live.add = slow_add
    assert eng.submit('mug', [_cloud(0)], 'first')[0]
    while eng.step(rec):
        pass
    assert started.wait(10)
    for i in range(600):
        assert eng.submit('cup', [_cloud(i)], f'm{i % 7}')[0]
    assert eng.save_later(str(tmp_path / 'b.npz')) is not None
    t0 = time.monotonic()
    eng.close()
    assert time.monotonic() - t0 < 2.0
    assert eng.pending() == 1                         # the one in progress, abandoned
    assert any('600 pending example(s) of 1 class(es) dropped, 1 forget/save request(s) not '
               'done' in text for text in logs), logs
    release.set()
    eng._committer.join(10)                           # noqa: SLF001
    assert changes == [] and eng.pending() == 0       # finished, but not published
    assert eng.counters['dropped'] == 600
    assert not eng.submit('cup', [_cloud(1)], 'late')[0]
    assert eng.save_later(str(tmp_path / 'b.npz')).result(1)[0] is False
    assert not (tmp_path / 'b.npz').exists()


def test_waiting_service_requests_are_bounded_and_all_answered(tmp_path: Path) -> None:
    """30 saves at once while the committer is busy: each is answered, the excess 'busy'."""
    from point_gn_ros.node.enroll_engine import MAX_SERVICE_OPS

    eng, live, changes = _engine(tmp_path)
    release, started = threading.Event(), threading.Event()
    real_save = live.save
    live.save = lambda *a, **k: (started.set(), release.wait(10), real_save(*a, **k))[2]
    futures = [eng.save_later(str(tmp_path / 'b0.npz'))]
    assert started.wait(10)                            # the committer is in the first
    futures += [eng.save_later(str(tmp_path / f'b{i}.npz')) for i in range(1, 30)]
    busy = [f for f in futures if f.done()]
    assert len(busy) == 30 - MAX_SERVICE_OPS - 1
    assert all(f.result()[0] is False and 'busy' in f.result()[1] for f in busy)
    release.set()
    results = [f.result(10) for f in futures]
    assert sum(ok for ok, _ in results) == MAX_SERVICE_OPS + 1
    assert eng.counters['busy'] == len(busy)
    eng.close()


def test_unpaired_detection_arrays_wait_in_a_bounded_list() -> None:
    from types import SimpleNamespace

    from point_gn_ros.node.enroll_detections import StampPairing

    def msg(sec: int) -> SimpleNamespace:
        return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=sec,
                                                                            nanosec=0)))
    pairing = StampPairing(5.0, max_waiting=4)
    for sec in range(10):                        # never paired: only the newest 4 wait
        assert pairing.add(msg(sec), None) == []
    assert pairing.expired == 6
    assert pairing.add(None, msg(9)) and not pairing.add(None, msg(0))
