"""Read a bank `.npz` with bounds: nothing is allocated or decompressed before it is checked.

`read_npz_bounded(path)` looks at the zip directory first: every member must be a `.npy`
whose uncompressed size (as the directory states it) fits, and all of them together at most
`BANK_MAX_BYTES`. Then each member's `.npy` header is read (a few hundred bytes
decompressed): a plain (no object) dtype whose shape times item size is exactly the member's
size. Only then is the array read, and zipfile never decompresses a member past the size
its directory entry states. So a header claiming 10^12 x 256 floats, or a zip bomb of a
gigabyte of zeros, is refused in milliseconds with one line (`BankError`), never a
MemoryError, a traceback or gigabytes of RSS. Never unpickles (allow_pickle=False).
"""

from __future__ import annotations

import os
from pathlib import Path
import zipfile

import numpy as np

from point_gn_ros.errors import BankError

# Uncompressed bytes of all arrays of one bank file together. The shipped bank holds ~25 MB;
# a 79k-row float32 scan section ~80 MB; a gigabyte is room for ~2 M float16 rows of 256.
BANK_MAX_BYTES = 1 << 30
# Members of one bank file at most (the largest bank format has ~40 arrays).
BANK_MAX_MEMBERS = 256

__all__ = ['BANK_MAX_BYTES', 'read_npz_bounded']


def read_npz_bounded(path: str | os.PathLike[str], max_bytes: int = BANK_MAX_BYTES
                     ) -> dict[str, np.ndarray]:
    """Every member of an .npz, name -> array; BankError('<path>: <reason>') otherwise."""
    path = Path(path)

    def fail(problem: str) -> BankError:
        return BankError(f'{path}: {problem}')

    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > BANK_MAX_MEMBERS:
                raise fail(f'{len(infos)} arrays, more than the limit of {BANK_MAX_MEMBERS}')
            total = 0
            for info in infos:
                if not info.filename.endswith('.npy') or info.is_dir():
                    raise fail(f'member {info.filename[:80]!r} is not an .npy array')
                total += info.file_size
            if total > max_bytes:
                raise fail(f'arrays hold {total:,} bytes uncompressed, more than the limit of '
                           f'{max_bytes:,} (read nothing)')
            arrays = {}
            for info in infos:
                name = info.filename[:-len('.npy')]
                if name in arrays:
                    raise fail(f'array {name[:80]!r} is stored twice')
                with zf.open(info) as f:
                    _check_header(f, info, fail)
                with zf.open(info) as f:
                    arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
            return arrays
    except BankError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError,
            NotImplementedError, RuntimeError) as exc:
        raise fail(f'unreadable or corrupt bank file ({type(exc).__name__}: '
                   f'{str(exc)[:200]})') from None


def _check_header(f, info: zipfile.ZipInfo, fail) -> None:  # noqa: ANN001
    """The member's .npy header: a plain dtype whose shape fills the member exactly."""
    name = info.filename
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f'npy format version {version}')
    except (ValueError, EOFError, SyntaxError) as exc:
        raise fail(f'{name}: not a valid .npy header ({str(exc)[:200]})') from None
    if dtype.hasobject:
        raise fail(f'{name}: holds Python objects (never unpickled)')
    count = 1
    for n in shape:
        count *= int(n)
    data = count * dtype.itemsize
    header = f.tell()
    if header + data != info.file_size:
        raise fail(f'{name}: header says {shape} {dtype} ({data:,} bytes), the member holds '
                   f'{max(0, info.file_size - header):,}')
