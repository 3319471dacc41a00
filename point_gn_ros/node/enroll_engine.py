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
  Consecutive adds of one class from one source are committed as one version.

Bounds: `pending()` counts every example from `submit` until it is committed (or dropped),
at most `max_pending`; one call takes at most `max_examples`; the bank holds at most
`max_classes` classes; at most MAX_SERVICE_OPS forget / save requests wait, more are
answered "busy" at once. `close()` drops whatever waits (one log line) and never waits
more than CLOSE_WAIT_S for the change in progress, which is then not published.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import Future, TimeoutError as FutureTimeout
from dataclasses import dataclass, field
import os
import threading
import time
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.enroll import EnrollError, EnrollResult
from point_gn_ros.bank.live import LiveBank, Snapshot
from point_gn_ros.bank.store import class_name_problem
from point_gn_ros.core.augment import variants_per_example
from point_gn_ros.core.fusion import with_fused
from point_gn_ros.core.threads import lower_priority, name_os_thread, trim_heap
from point_gn_ros.errors import PointGNError

# How long a service waits for the committer (forget, save) before answering "still running".
SERVICE_TIMEOUT_S = 30.0
# Forget / save requests waiting for the committer at most; more are answered "busy".
MAX_SERVICE_OPS = 4
# At shutdown, how long close() lets the committer finish the change it is applying.
CLOSE_WAIT_S = 1.0
# The committer's changes that services ask for (bounded by MAX_SERVICE_OPS).
_SERVICE_KINDS = ('remove', 'save')


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
class _Op:
    """One change for the committer: add (encoded requests), remove, save or flush."""

    kind: str
    reqs: list[_Request] = field(default_factory=list)
    args: tuple[Any, ...] = ()
    future: Future | None = None

    @property
    def examples(self) -> int:
        return sum(len(r.clouds) for r in self.reqs)


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
                 min_points: int = 16, augment: str = 'none', fuse_views: bool = False,
                 max_classes: int = 256, max_examples: int = 200) -> None:
        self.live = live
        self.augment, self.fuse_views = augment, fuse_views
        self.chunk = max(1, chunk // variants_per_example(augment))
        self.max_pending = max_pending
        self.max_classes, self.max_examples = max_classes, max_examples
        self.capture_max, self.min_points = capture_max, min_points
        self._on_change, self._log, self._warn = on_change, log, warn
        self._lock = threading.Condition()   # requests, ops, pending, capture, closed
        self._count_lock = threading.Lock()
        self._requests: deque[_Request] = deque()
        self._ops: deque[_Op] = deque()
        self._service_ops = 0
        self._pending = 0
        self._closed = False
        self._capture: _Capture | None = None
        self._committer = threading.Thread(target=self._commit_loop, name='point_gn_enroll',
                                           daemon=True)
        self.counters = {'enrolled': 0, 'enrollments': 0, 'refused': 0, 'dropped': 0,
                         'near_duplicates': 0, 'removed_classes': 0, 'saves': 0, 'busy': 0,
                         'errors': 0, 'fused': 0, 'not_fused': 0}
        self.refused_by: dict[str, int] = {}      # reason -> examples refused
        self.last_latency_s = float('nan')
        self.last_save: tuple[str, int] | None = None
        self.last_error = ''
        self._committer.start()

    # ------------------------------------------------------------------ producers

    def submit(self, class_name: str, clouds: Sequence[np.ndarray], source: str,
               fuse: bool = False) -> tuple[bool, str]:
        """Queue examples (z-up (N_i, 3) float32 clouds) of one class; -> (accepted, why).

        fuse: the clouds are views of one object in one fixed frame (core/fusion.py): one
        request of its own, fused on the worker before it is encoded.
        """
        name = class_name.strip()
        problem = class_name_problem(name)        # the rule the saved bank is loaded with
        if problem:
            return self.refuse(len(clouds), problem, 'class_name')
        if len(clouds) > self.max_examples:
            self.refuse(len(clouds) - self.max_examples, f'one request of {name[:60]!r} '
                        f'holds {len(clouds)} examples, max {self.max_examples}', 'per_call')
            clouds = clouds[:self.max_examples]
        small = [len(c) for c in clouds if len(c) < self.min_points]
        clouds = [c for c in clouds if len(c) >= self.min_points]
        if small:
            self.refuse(len(small), f'{len(small)} example(s) of {name[:60]!r} have fewer '
                                     f'than min_points={self.min_points} points', 'too_few_points')
        if not clouds:
            return False, 'no usable example'
        with self._lock:
            if self._closed:
                why, reason = 'the node is shutting down', 'shutting_down'
            elif self._pending + len(clouds) > self.max_pending:
                why, reason = (f'{self._pending} examples already waiting (max '
                               f'{self.max_pending})'), 'queue_full'
            elif not self._room_for(name):
                why, reason = (f'{name[:60]!r} would be a new class beyond '
                               f'enroll_max_classes={self.max_classes}'), 'class_limit'
            else:
                last = self._requests[-1] if self._requests else None
                if not fuse and last is not None and not last.fuse and \
                        last.class_name == name and last.source == source and \
                        len(last.clouds) + len(clouds) <= self.max_examples:
                    # Examples streaming in (one per message): one enrollment, one version.
                    last.clouds.extend(clouds)
                else:
                    self._requests.append(_Request(name, list(clouds), source, fuse=fuse))
                self._pending += len(clouds)
                return True, f'{len(clouds)} example(s) of {name!r} queued'
        return self.refuse(len(clouds), why, reason)

    def _room_for(self, name: str) -> bool:
        """Whether `name` fits the class cap with every class already waiting (locked)."""
        names = self.live.current().class_names
        if name in names:
            return True
        waiting = {r.class_name for r in self._requests}
        waiting.update(r.class_name for op in self._ops for r in op.reqs)
        if name in waiting:
            return True
        return len(names) + len(waiting - set(names)) < self.max_classes

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
        """Queue the removal of a class on the committer -> Future of (ok, message).

        Answered at once with (False, 'busy ...') when MAX_SERVICE_OPS already wait.
        """
        return self._service_op('remove', class_name.strip(), source)

    def save(self, path: str) -> tuple[bool, str]:
        """Atomically write the current version to path (in order with commits); waits."""
        return self._wait(self.save_later(path))

    def save_later(self, path: str) -> Future:
        """Queue an atomic save of the current version -> Future of (ok, message)."""
        if not path:
            return _done(False, 'set the save_bank_path parameter first')
        return self._service_op('save', path)

    def _service_op(self, kind: str, *args: Any) -> Future:
        with self._lock:
            if self._closed:
                return _done(False, 'the node is shutting down')
            if self._service_ops >= MAX_SERVICE_OPS:
                busy = self._service_ops
            else:
                fut: Future = Future()
                self._service_ops += 1
                self._ops.append(_Op(kind, args=args, future=fut))
                self._lock.notify_all()
                return fut
        self._count('busy', 1)
        return _done(False, f'busy: {busy} forget/save requests are waiting (max '
                            f'{MAX_SERVICE_OPS}); try again later')

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
            if not self._requests or self._closed:
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
            if req.encoded >= len(req.clouds) and self._requests and \
                    self._requests[0] is req:
                # Still pending (counted) until committed: the committer takes it in order.
                self._requests.popleft()
                self._ops.append(_Op('add', [req]))
                self._lock.notify_all()
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

    def _commit_loop(self) -> None:
        """Committer thread: apply the queued changes in order until closed."""
        name_os_thread()
        lower_priority()          # refits yield the CPU to the worker's answers
        while True:
            with self._lock:
                while not self._ops and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                op = self._ops.popleft()
                while op.kind == 'add' and self._ops and self._ops[0].kind == 'add' and \
                        self._ops[0].reqs[0].class_name == op.reqs[0].class_name and \
                        self._ops[0].reqs[0].source == op.reqs[0].source:
                    op.reqs += self._ops.popleft().reqs     # one version for a stream
                if op.kind in _SERVICE_KINDS:
                    self._service_ops -= 1
            try:
                result = self._apply(op)
            except Exception as exc:  # noqa: BLE001 - the committer must outlive one change
                self.report_error(f'enrollment {op.kind} failed: {type(exc).__name__}: {exc}')
                result = (False, f'{op.kind} failed: {type(exc).__name__}: {exc}')
            finally:
                if op.kind == 'add':
                    with self._lock:
                        self._pending -= op.examples
            if op.future is not None and not op.future.done():
                op.future.set_result(result)
            if op.kind in ('add', 'remove'):
                trim_heap()       # the versions it replaced: memory back to the OS

    def _apply(self, op: _Op) -> tuple[bool, str]:
        if op.kind == 'add':
            self._commit(op.reqs)
            return True, ''
        if op.kind == 'remove':
            return self._remove(*op.args)
        if op.kind == 'save':
            return self._save(*op.args)
        return True, ''                           # flush

    def _commit(self, reqs: list[_Request]) -> None:
        req = reqs[0]
        n = sum(len(r.clouds) for r in reqs)
        if self._closed:
            return
        if req.class_name not in self.live.current().class_names and \
                len(self.live.current().class_names) >= self.max_classes:
            self.refuse(n, f'{req.class_name[:60]!r} would be a new class beyond '
                           f'enroll_max_classes={self.max_classes}', 'class_limit')
            return
        source = req.source if len(reqs) == 1 else f'{req.source} ({len(reqs)} requests)'
        try:
            parts = [s for r in reqs for s in r.sizes]
            sizes = None if any(s is None for s in parts) else np.concatenate(parts)
            res = self.live.add(torch.cat([f for r in reqs for f in r.feats]), req.class_name,
                                source, augment=self.augment, sizes=sizes)
        except (EnrollError, PointGNError, ValueError) as exc:
            self.report_error(f'enrollment of {req.class_name[:60]!r} refused: {exc}')
            return
        except Exception as exc:  # noqa: BLE001 - the committer must outlive one request
            self.report_error(f'enrollment of {req.class_name[:60]!r} failed: '
                              f'{type(exc).__name__}: {exc}')
            return
        if self._closed:
            return                # shut down meanwhile: not published, not logged
        self.last_latency_s = time.monotonic() - req.received
        self._count('enrolled', res.examples)
        self._count('enrollments', 1)
        self._count('near_duplicates', res.duplicate_count)
        self._changed(res)
        self._log(f'{res.describe()} in {self.last_latency_s:.2f} s ({source})')
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
            written, version = self.live.save(path, make_dirs=False)   # no new folders
        except (OSError, PointGNError, ValueError) as exc:
            self.report_error(f'saving the bank to {path} failed: {exc}')
            return False, f'saving to {path} failed: {exc}'
        self._count('saves', 1)
        self.last_save = (str(written), version)
        text = f'bank v{version} saved to {os.fspath(written)} in {time.monotonic() - t0:.2f} s'
        self._log(text)
        return True, text

    def _changed(self, res: EnrollResult) -> None:
        if self._closed:
            return                # shut down: the node's publishers are going away
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
        fut: Future = Future()
        with self._lock:
            if self._closed:
                return
            self._ops.append(_Op('flush', future=fut))
            self._lock.notify_all()
        fut.result(timeout)

    def set_log(self, log: Callable[[str], object]) -> None:
        """Another info sink (the node's logger is gone once its context is shut down)."""
        self._log = log

    def close(self) -> None:
        """Stop now: drop what waits (one log line), wait at most CLOSE_WAIT_S, publish nothing.

        A change the committer is applying when this is called is abandoned unpublished if
        it does not finish within CLOSE_WAIT_S (the committer is a daemon thread).
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            reqs = list(self._requests) + [r for op in self._ops for r in op.reqs]
            waiting = [op for op in self._ops if op.future is not None]
            self._requests.clear()
            self._ops.clear()
            self._capture = None
            dropped = sum(len(r.clouds) for r in reqs)
            self._pending -= dropped
            self._lock.notify_all()
        for op in waiting:
            if not op.future.done():
                op.future.set_result((False, 'the node is shutting down: not done'))
        services = [op for op in waiting if op.kind in _SERVICE_KINDS]
        if dropped or services:
            self._count('dropped', dropped)
            self._log(f'enrollment stopped: {dropped} pending example(s) of '
                      f'{len({r.class_name for r in reqs})} class(es) dropped, '
                      f'{len(services)} forget/save request(s) not done')
        if threading.current_thread() is not self._committer:
            self._committer.join(CLOSE_WAIT_S)
            if self._committer.is_alive():
                self._log(f'enrollment: the change in progress did not finish within '
                          f'{CLOSE_WAIT_S:g} s; it is abandoned (not published)')

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
        self.refuse(len(req.clouds), f'{req.class_name[:60]!r}: {why}', 'encoding_failed')

    def refuse(self, count: int, why: str, reason: str = 'other') -> tuple[bool, str]:
        """Count `count` refused examples under `reason` and warn (rate-limited per reason)."""
        self._count('refused', count)
        with self._count_lock:
            self.refused_by[reason] = self.refused_by.get(reason, 0) + count
        self._warn(('refused', reason), f'enrollment: {count} example(s) refused: {why}')
        return False, why

    def _count(self, key: str, n: int) -> None:
        with self._count_lock:
            self.counters[key] += n

    def report_error(self, text: str) -> None:
        """Count an enrollment error (diagnostics `enroll_errors`) and warn, rate-limited."""
        self._count('errors', 1)
        self.last_error = text
        self._warn(('error',), text)


def _done(ok: bool, message: str) -> Future:
    fut: Future = Future()
    fut.set_result((ok, message))
    return fut
