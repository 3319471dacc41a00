"""The node's live enrollment, without ROS: requests, capture, chunked encoding, commits.

Threads and who does what:
- producers (subscription / service callbacks, any thread) `submit` object clouds under a
  class, or `start_capture` / `stop_capture`; nothing heavy happens there;
- the classifier's worker calls `observe(jobs)` after preparing each micro-batch (capture)
  and `step(recognizer)` between micro-batches: it encodes at most `chunk` waiting examples
  with the same encoder, so enrollment delays answers by at most one micro-batch's worth of
  encoding, and never drops or reorders them;
- one committer thread applies every change in order (add, remove, save): the refit and the
  copy-on-write bank build (bank/enroll.py) run there, then `on_change(snapshot, result)`
  hands the new version to the node, which swaps it in between two micro-batches.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, TimeoutError as FutureTimeout
from dataclasses import dataclass, field
import os
import threading
import time
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.enroll import EnrollError, EnrollResult
from point_gn_ros.bank.live import LiveBank, Snapshot
from point_gn_ros.core.augment import variants_per_example
from point_gn_ros.core.fusion import with_fused
from point_gn_ros.core.threads import name_os_thread
from point_gn_ros.errors import PointGNError

# How long a service waits for the committer (forget, save) before answering "still running".
SERVICE_TIMEOUT_S = 30.0


@dataclass
class _Request:
    """Examples of one class waiting to be encoded, then committed as one enrollment."""

    class_name: str
    clouds: list[np.ndarray]           # (N_i, 3) float32, z-up
    source: str
    received: float = field(default_factory=time.monotonic)
    feats: list[torch.Tensor] = field(default_factory=list)
    sizes: list[np.ndarray | None] = field(default_factory=list)  # (n, SIZE_DIM) or None
    encoded: int = 0
    fuse: bool = False                 # views of one object: fused on the worker first


@dataclass
class _Capture:
    class_name: str
    topics: frozenset[int] | None      # None = every input topic
    clouds: list[np.ndarray] = field(default_factory=list)
    overflow: int = 0


class EnrollEngine:
    """See the module docstring.

    live: the node's LiveBank (model = Recognizer); on_change(snapshot, result): called on
    the committer thread after every published version; log(text) / warn(key, text): info
    and rate-limited warning sinks; chunk: examples encoded per worker step; max_pending:
    examples waiting at most (beyond it a submission is refused and counted); capture_max:
    objects one capture keeps at most; min_points: smaller examples are refused; augment:
    the frames each example is stored in (core/augment.py; k encodings per example, so a
    worker step encodes chunk // k examples and still costs about one micro-batch);
    fuse_views: a capture's objects are views of one object in one fixed frame, fused into
    more examples (core/fusion.py) in a worker step of their own before encoding.
    """

    def __init__(self, live: LiveBank, on_change: Callable[[Snapshot, EnrollResult], None],
                 log: Callable[[str], object], warn: Callable[[Hashable, str], object],
                 chunk: int = 32, max_pending: int = 512, capture_max: int = 200,
                 min_points: int = 16, augment: str = 'none', fuse_views: bool = False) -> None:
        self.live = live
        self.augment, self.fuse_views = augment, fuse_views
        self.chunk = max(1, chunk // variants_per_example(augment))
        self.max_pending = max_pending
        self.capture_max, self.min_points = capture_max, min_points
        self._on_change, self._log, self._warn = on_change, log, warn
        self._lock = threading.Lock()
        self._count_lock = threading.Lock()
        self._requests: deque[_Request] = deque()
        self._pending = 0
        self._capture: _Capture | None = None
        self._committer = ThreadPoolExecutor(max_workers=1, thread_name_prefix='point_gn_enroll',
                                             initializer=name_os_thread)
        self.counters = {'enrolled': 0, 'enrollments': 0, 'refused': 0, 'near_duplicates': 0,
                         'removed_classes': 0, 'saves': 0, 'errors': 0, 'fused': 0,
                         'not_fused': 0}
        self.last_latency_s = float('nan')
        self.last_save: tuple[str, int] | None = None
        self.last_error = ''

    # ------------------------------------------------------------------ producers

    def submit(self, class_name: str, clouds: Sequence[np.ndarray], source: str,
               fuse: bool = False) -> tuple[bool, str]:
        """Queue examples (z-up (N_i, 3) float32 clouds) of one class; -> (accepted, why).

        fuse: the clouds are views of one object in one fixed frame (core/fusion.py): one
        request of its own, fused on the worker before it is encoded.
        """
        name = class_name.strip()
        if not name:
            return self.refuse(len(clouds), 'empty class name')
        small = [len(c) for c in clouds if len(c) < self.min_points]
        clouds = [c for c in clouds if len(c) >= self.min_points]
        if small:
            self.refuse(len(small), f'{len(small)} example(s) of {name!r} have fewer than '
                                     f'min_points={self.min_points} points')
        if not clouds:
            return False, 'no usable example'
        with self._lock:
            if self._pending + len(clouds) > self.max_pending:
                pending = self._pending
            else:
                last = self._requests[-1] if self._requests else None
                if not fuse and last is not None and not last.fuse and \
                        last.class_name == name and last.source == source:
                    # Examples streaming in (one per message): one enrollment, one version.
                    last.clouds.extend(clouds)
                else:
                    self._requests.append(_Request(name, list(clouds), source, fuse=fuse))
                self._pending += len(clouds)
                return True, f'{len(clouds)} example(s) of {name!r} queued'
        return self.refuse(len(clouds), f'{pending} examples already waiting (max '
                                         f'{self.max_pending})')

    def start_capture(self, class_name: str, topics: frozenset[int] | None) -> tuple[bool, str]:
        name = class_name.strip()
        if not name:
            return False, 'set the enroll_class parameter first'
        with self._lock:
            if self._capture is not None:
                return False, f'already capturing {self._capture.class_name!r}'
            self._capture = _Capture(name, topics)
        return True, f'capturing objects as {name!r}'

    def stop_capture(self) -> tuple[bool, str]:
        with self._lock:
            cap, self._capture = self._capture, None
        if cap is None:
            return False, 'not capturing'
        if not cap.clouds:
            return False, f'no object was captured for {cap.class_name!r}'
        over = f', {cap.overflow} more over capture_max' if cap.overflow else ''
        return self.submit(cap.class_name, cap.clouds,
                           f'capture of {len(cap.clouds)} object(s){over}', fuse=self.fuse_views)

    def forget(self, class_name: str, source: str) -> tuple[bool, str]:
        """Remove a class (on the committer, in order with pending commits); waits for it."""
        return self._wait(self.forget_later(class_name, source))

    def forget_later(self, class_name: str, source: str) -> Future:
        """Queue the removal of a class on the committer -> Future of (ok, message)."""
        return self._committer.submit(self._remove, class_name.strip(), source)

    def save(self, path: str) -> tuple[bool, str]:
        """Atomically write the current version to path (in order with commits); waits."""
        return self._wait(self.save_later(path))

    def save_later(self, path: str) -> Future:
        """Queue an atomic save of the current version -> Future of (ok, message)."""
        if not path:
            done: Future = Future()
            done.set_result((False, 'set the save_bank_path parameter first'))
            return done
        return self._committer.submit(self._save, path)

    # ------------------------------------------------------------------ worker hooks

    def observe(self, topic_index: int, clouds: Sequence[np.ndarray]) -> None:
        """Worker: objects (z-up) just prepared from input topic `topic_index`."""
        cap = self._capture
        if cap is None or (cap.topics is not None and topic_index not in cap.topics):
            return
        with self._lock:
            room = self.capture_max - len(cap.clouds)
            cap.clouds.extend(clouds[:max(0, room)])
            cap.overflow += max(0, len(clouds) - max(0, room))

    def step(self, recognizer: Any) -> bool:
        """Worker, between micro-batches: encode up to `chunk` waiting examples.

        Returns whether there is more to do. A finished request goes to the committer.
        """
        with self._lock:
            if not self._requests:
                return False
            req = self._requests[0]
            todo = req.clouds[req.encoded:req.encoded + self.chunk]
        if req.fuse:
            self._fuse(req)
            return True
        try:
            req.feats.append(recognizer.encode(todo, augment=self.augment))
            req.sizes.append(recognizer.sizes(todo))  # metric size (core/size.py) or None
        except Exception as exc:  # noqa: BLE001 - one bad example costs its request only
            self._drop_head(req, f'encoding failed: {type(exc).__name__}: {exc}')
            return bool(self._requests)
        with self._lock:          # submit() may still be extending this request
            req.encoded += len(todo)
            done = req.encoded >= len(req.clouds)
            if done:
                self._requests.popleft()
                self._pending -= len(req.clouds)
        if done:
            self._committer.submit(self._commit, req)
        return bool(self._requests)

    def _fuse(self, req: _Request) -> None:
        """Worker: a capture's views and what fusing them adds (one step of its own)."""
        try:
            clouds, note = with_fused(req.clouds)
        except Exception as exc:  # noqa: BLE001 - the views are still enrolled as they are
            clouds, note = req.clouds, f'not fused: {type(exc).__name__}: {exc}'
        with self._lock:          # a fuse request is never extended by submit()
            added = len(clouds) - len(req.clouds)
            req.clouds, req.fuse = clouds, False
            self._pending += added
            req.source = f'{req.source}; {note}'
        self._count('fused' if added else 'not_fused', 1)
        if not added:
            self._warn(('not_fused',), f'enrollment of {req.class_name!r}: {note}')

    # ------------------------------------------------------------------ committer

    def _commit(self, req: _Request) -> None:
        try:
            sizes = None if any(s is None for s in req.sizes) else np.concatenate(req.sizes)
            res = self.live.add(torch.cat(req.feats), req.class_name, req.source,
                                augment=self.augment, sizes=sizes)
        except (EnrollError, PointGNError, ValueError) as exc:
            self.report_error(f'enrollment of {req.class_name!r} refused: {exc}')
            return
        except Exception as exc:  # noqa: BLE001 - the committer must outlive one request
            self.report_error(f'enrollment of {req.class_name!r} failed: '
                              f'{type(exc).__name__}: {exc}')
            return
        self.last_latency_s = time.monotonic() - req.received
        self._count('enrolled', res.examples)
        self._count('enrollments', 1)
        self._count('near_duplicates', res.duplicate_count)
        self._changed(res)
        self._log(f'{res.describe()} in {self.last_latency_s:.2f} s ({req.source})')
        if res.duplicate_count:
            pairs = '; '.join(f'#{d.index} ~ {d.other} ({d.cosine:.4f})'
                              for d in res.duplicates[:5])
            self._warn(('duplicates', req.class_name),
                       f'{res.duplicate_count} near-duplicate example(s) enrolled as '
                       f'{req.class_name!r}: {pairs}')

    def _remove(self, class_name: str, source: str) -> tuple[bool, str]:
        try:
            res = self.live.remove(class_name, source)
        except (EnrollError, PointGNError) as exc:
            return False, str(exc)
        self._count('removed_classes', 1)
        self._changed(res)
        self._log(res.describe())
        return True, res.describe()

    def _save(self, path: str) -> tuple[bool, str]:
        t0 = time.monotonic()
        try:
            written, version = self.live.save(path)
        except (OSError, PointGNError, ValueError) as exc:
            self.report_error(f'saving the bank to {path} failed: {exc}')
            return False, f'saving to {path} failed: {exc}'
        self._count('saves', 1)
        self.last_save = (str(written), version)
        text = f'bank v{version} saved to {os.fspath(written)} in {time.monotonic() - t0:.2f} s'
        self._log(text)
        return True, text

    def _changed(self, res: EnrollResult) -> None:
        try:
            self._on_change(self.live.current(), res)
        except Exception as exc:  # noqa: BLE001 - the bank changed; reporting it must not undo it
            self.report_error(f'publishing bank v{res.version} failed: '
                              f'{type(exc).__name__}: {exc}')

    # ------------------------------------------------------------------ misc

    def pending(self) -> int:
        return self._pending

    def capturing(self) -> str:
        cap = self._capture
        return '' if cap is None else f'{cap.class_name} ({len(cap.clouds)})'

    def flush(self, timeout: float = SERVICE_TIMEOUT_S) -> None:
        """Wait until every change handed to the committer so far is applied."""
        self._committer.submit(lambda: None).result(timeout)

    def close(self) -> None:
        """Finish queued commits (bounded by their own work) and stop the committer."""
        self._committer.shutdown(wait=True, cancel_futures=True)

    def _wait(self, fut: Future) -> tuple[bool, str]:
        try:
            return fut.result(SERVICE_TIMEOUT_S)
        except FutureTimeout:
            return False, f'still running after {SERVICE_TIMEOUT_S:g} s (see the log)'

    def _drop_head(self, req: _Request, why: str) -> None:
        with self._lock:
            if self._requests and self._requests[0] is req:
                self._requests.popleft()
                self._pending -= len(req.clouds)
        self.refuse(len(req.clouds), f'{req.class_name!r}: {why}')

    def refuse(self, count: int, why: str) -> tuple[bool, str]:
        """Count `count` refused examples and warn (rate-limited per reason)."""
        self._count('refused', count)
        self._warn(('refused', why.split(':')[0]),
                   f'enrollment: {count} example(s) refused: {why}')
        return False, why

    def _count(self, key: str, n: int) -> None:
        with self._count_lock:
            self.counters[key] += n

    def report_error(self, text: str) -> None:
        """Count an enrollment error (diagnostics `enroll_errors`) and warn, rate-limited."""
        self._count('errors', 1)
        self.last_error = text
        self._warn(('error',), text)
