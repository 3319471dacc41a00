"""Bank rows that grow by appending without copying the whole bank each version.

An enrollment's bank is the previous version's rows plus a few new ones. Concatenating
copies every row (a scan section of 39,372 x 320 float32: 50 MB, ~45 ms of CPU per
enrollment, more on a loaded machine). Instead the rows live in a buffer with spare room
after them: version k's features are a view of the buffer's first n_k rows, and the next
version writes its new rows after them and views n_k + m rows.

Copy-on-write still holds: a row once visible to a published version is never written
again. Only the version whose rows end where the buffer's claimed rows end may append in
place (claimed under a lock); any other (an older version appended to again, a branch) gets
a fresh buffer, as a copy would.
"""

from __future__ import annotations

import threading

import torch

# Spare rows allocated beyond the rows in use: this share of them, at least _MIN_SPARE.
# Untouched pages of a large allocation cost no memory until an append writes them.
_SPARE_SHARE = 0.125
_MIN_SPARE = 256


class _Buffer:
    """(capacity, d) rows of which the first `claimed` are in use by some version."""

    def __init__(self, n: int, tail: tuple[int, ...], dtype: torch.dtype) -> None:
        spare = max(_MIN_SPARE, int(n * _SPARE_SHARE))
        self.data = torch.empty((n + spare, *tail), dtype=dtype)
        self.claimed = n
        self.lock = threading.Lock()

    @classmethod
    def of(cls, rows: torch.Tensor, extra: torch.Tensor) -> '_Buffer':
        """A buffer holding rows then extra (same trailing shape and dtype)."""
        n0 = rows.shape[0]
        buf = cls(n0 + extra.shape[0], tuple(rows.shape[1:]), rows.dtype)
        buf.data[:n0] = rows
        buf.data[n0:buf.claimed] = extra
        return buf


def append_rows(rows: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """torch.cat([rows, new]) (rows (N, d), new (M, d), CPU): in place when it is safe.

    The result is a view of a shared buffer (module docstring); `rows` and every earlier
    version keep exactly the values they had.
    """
    new = new.to(dtype=rows.dtype)
    if rows.device.type != 'cpu' or new.shape[1:] != rows.shape[1:]:
        return torch.cat([rows, new])
    buf: _Buffer | None = getattr(rows, '_pgn_rows', None)
    n, m = rows.shape[0], new.shape[0]
    if buf is not None and rows.data_ptr() == buf.data.data_ptr() and rows.is_contiguous():
        with buf.lock:
            ok = buf.claimed == n and n + m <= buf.data.shape[0]
            if ok:
                buf.claimed = n + m
        if ok:
            buf.data[n:n + m] = new
            return _view(buf, n + m)
    return _view(_Buffer.of(rows, new), n + m)


def with_room(rows: torch.Tensor) -> torch.Tensor:
    """The same values (N, d) in a buffer with spare room, so the first append is in place.

    For a bank about to take enrollments (bank/live.py): the one copy happens here, once
    (none for rows `FeatureBank.load` made, which already have room).
    """
    if rows.device.type != 'cpu' or getattr(rows, '_pgn_rows', None) is not None:
        return rows
    return _view(_Buffer.of(rows, rows[:0]), rows.shape[0])


def empty_rows(n: int, d: int) -> torch.Tensor:
    """(n, d) float32, uninitialised, in a buffer with spare room: fill it before use.

    What `FeatureBank.load` fills, so a bank about to take enrollments needs no second copy
    of its rows (`with_room` returns them as they are).
    """
    return _view(_Buffer(n, (d,), torch.float32), n)


def _view(buf: _Buffer, n: int) -> torch.Tensor:
    out = buf.data[:n]
    out._pgn_rows = buf          # the next append finds its buffer here
    return out
