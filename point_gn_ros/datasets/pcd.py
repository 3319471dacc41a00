"""PCD reader (PCL Point Cloud Data, header v.5 and v0.7): ascii, binary, binary_compressed."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from point_gn_ros.datasets import lzf
from point_gn_ros.datasets._common import PathLike, read_bytes, with_xyz
from point_gn_ros.errors import DatasetError

# (TYPE, SIZE) -> numpy type code; PCD data is little-endian.
_TYPES = {('F', 4): '<f4', ('F', 8): '<f8',
          ('I', 1): 'i1', ('I', 2): '<i2', ('I', 4): '<i4', ('I', 8): '<i8',
          ('U', 1): 'u1', ('U', 2): '<u2', ('U', 4): '<u4', ('U', 8): '<u8'}
_ENCODINGS = ('ascii', 'binary', 'binary_compressed')
_MAX_HEADER = 1 << 16  # a PCD header is a dozen short lines; stop early on non-PCD files


@dataclass
class PcdHeader:
    """Parsed PCD header. `data_offset` is where the point data starts in the file."""

    version: str = ''
    fields: list[str] = field(default_factory=list)
    sizes: list[int] = field(default_factory=list)
    types: list[str] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)
    width: int = 0
    height: int = 1
    viewpoint: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    points: int = 0
    data: str = ''
    data_offset: int = 0

    def column_dtypes(self) -> list[np.dtype]:
        """One numpy dtype per field (its scalar type, little-endian)."""
        return [np.dtype(_TYPES[(t, s)]) for t, s in zip(self.types, self.sizes, strict=True)]

    @property
    def point_size(self) -> int:
        """Bytes per point in the binary layout."""
        return sum(s * c for s, c in zip(self.sizes, self.counts, strict=True))

    def record_dtype(self) -> np.dtype:
        """Packed structured dtype of one point; '_' padding fields get unique names."""
        items = []
        for i, (name, dt, count) in enumerate(zip(self.fields, self.column_dtypes(),
                                                  self.counts, strict=True)):
            key = f'_pad{i}' if name == '_' else name
            items.append((key, dt, (count,)) if count > 1 else (key, dt))
        return np.dtype(items)


def _parse_header(raw: bytes, path: PathLike) -> PcdHeader:
    """Header lines up to and including DATA -> PcdHeader, validating consistency."""
    hdr = PcdHeader()
    seen: set[str] = set()
    pos = 0
    while True:
        end = raw.find(b'\n', pos, pos + _MAX_HEADER)
        if end < 0:
            raise DatasetError(f'{path}: bad PCD header: no DATA line')
        try:
            line = raw[pos:end].decode('ascii').strip()
        except UnicodeDecodeError:
            raise DatasetError(f'{path}: bad PCD header: not a PCD file '
                               '(binary bytes before the DATA line)') from None
        pos = end + 1
        if not line or line.startswith('#'):
            continue
        key, *vals = line.split()
        key = key.upper()
        try:
            if key == 'VERSION':
                hdr.version = vals[0] if vals else ''
            elif key in ('FIELDS', 'COLUMNS'):
                hdr.fields = vals
            elif key == 'SIZE':
                hdr.sizes = [int(v) for v in vals]
            elif key == 'TYPE':
                hdr.types = [v.upper() for v in vals]
            elif key == 'COUNT':
                hdr.counts = [int(v) for v in vals]
            elif key == 'WIDTH':
                (hdr.width,) = (int(v) for v in vals)
            elif key == 'HEIGHT':
                (hdr.height,) = (int(v) for v in vals)
            elif key == 'VIEWPOINT':
                hdr.viewpoint = tuple(float(v) for v in vals)
            elif key == 'POINTS':
                (hdr.points,) = (int(v) for v in vals)
            elif key == 'DATA':
                (hdr.data,) = (v.lower() for v in vals)
                hdr.data_offset = pos
                seen.add(key)
                break
            else:
                raise DatasetError(f'{path}: bad PCD header: unknown line {line!r}')
        except ValueError:
            raise DatasetError(f'{path}: bad PCD header line {line!r}') from None
        seen.add('FIELDS' if key == 'COLUMNS' else key)
    _check_header(hdr, seen, path)
    return hdr


def _check_header(hdr: PcdHeader, seen: set[str], path: PathLike) -> None:
    """Raise DatasetError unless the header fields agree with each other."""
    for key in ('FIELDS', 'SIZE', 'TYPE', 'WIDTH'):
        if key not in seen:
            raise DatasetError(f'{path}: bad PCD header: no {key} line')
    if 'COUNT' not in seen:
        hdr.counts = [1] * len(hdr.fields)
    if 'POINTS' not in seen:
        hdr.points = hdr.width * hdr.height
    n = len(hdr.fields)
    if not (len(hdr.sizes) == len(hdr.types) == len(hdr.counts) == n) or n == 0:
        raise DatasetError(f'{path}: bad PCD header: FIELDS/SIZE/TYPE/COUNT lengths '
                           f'{n}/{len(hdr.sizes)}/{len(hdr.types)}/{len(hdr.counts)} differ')
    for name, t, s, c in zip(hdr.fields, hdr.types, hdr.sizes, hdr.counts, strict=True):
        if (t, s) not in _TYPES:
            raise DatasetError(f'{path}: bad PCD header: field {name!r} has TYPE {t} SIZE {s}')
        if c < 1:
            raise DatasetError(f'{path}: bad PCD header: field {name!r} has COUNT {c}')
    named = [f for f in hdr.fields if f != '_']
    if len(set(named)) != len(named):
        raise DatasetError(f'{path}: bad PCD header: repeated field names {hdr.fields}')
    if hdr.width < 0 or hdr.height < 0 or hdr.points != hdr.width * hdr.height:
        raise DatasetError(f'{path}: bad PCD header: POINTS {hdr.points} != '
                           f'WIDTH {hdr.width} x HEIGHT {hdr.height}')
    if hdr.data not in _ENCODINGS:
        raise DatasetError(f'{path}: bad PCD header: DATA {hdr.data!r} is not one of '
                           f'{", ".join(_ENCODINGS)}')


def read_pcd_header(path: PathLike) -> PcdHeader:
    """Only the header of a PCD file (reads the whole file; headers are small)."""
    return _parse_header(read_bytes(path), path)


def _columns_ascii(raw: bytes, hdr: PcdHeader, path: PathLike) -> list[np.ndarray]:
    """ASCII data -> one (N, count) array per field."""
    width = sum(hdr.counts)
    try:
        values = np.array(raw[hdr.data_offset:].split(), dtype=np.float64)
    except ValueError:
        raise DatasetError(f'{path}: ascii PCD data has a non-numeric value') from None
    if values.size != hdr.points * width:
        raise DatasetError(f'{path}: ascii PCD data has {values.size} values, header says '
                           f'{hdr.points} points x {width} values')
    table = values.reshape(hdr.points, width)
    cols, start = [], 0
    with np.errstate(invalid='ignore', over='ignore'):
        for dt, c in zip(hdr.column_dtypes(), hdr.counts, strict=True):
            cols.append(table[:, start:start + c].astype(dt))
            start += c
    return cols


def _columns_binary(raw: bytes, hdr: PcdHeader, path: PathLike) -> list[np.ndarray]:
    """Point-major packed records -> one (N, count) array per field."""
    need = hdr.points * hdr.point_size
    have = len(raw) - hdr.data_offset
    if have < need:
        raise DatasetError(f'{path}: binary PCD data truncated: {have} bytes, header says '
                           f'{hdr.points} points x {hdr.point_size} bytes = {need}')
    rec = np.frombuffer(raw, dtype=hdr.record_dtype(), count=hdr.points, offset=hdr.data_offset)
    return [rec[name].reshape(hdr.points, c).copy()
            for name, c in zip(rec.dtype.names, hdr.counts, strict=True)]


def _columns_compressed(raw: bytes, hdr: PcdHeader, path: PathLike) -> list[np.ndarray]:
    """LZF-compressed field-major data -> one (N, count) array per field."""
    payload = memoryview(raw)[hdr.data_offset:]
    if len(payload) < 8:
        raise DatasetError(f'{path}: binary_compressed PCD data truncated: no size words')
    comp_size, raw_size = struct.unpack('<II', payload[:8])
    need = hdr.points * hdr.point_size
    if raw_size != need:
        raise DatasetError(f'{path}: binary_compressed size mismatch: uncompressed size '
                           f'{raw_size} bytes, header says {hdr.points} points x '
                           f'{hdr.point_size} bytes = {need}')
    if len(payload) - 8 < comp_size:
        raise DatasetError(f'{path}: binary_compressed PCD data truncated: '
                           f'{len(payload) - 8} of {comp_size} compressed bytes present')
    try:
        data = lzf.decompress(payload[8:8 + comp_size], raw_size) if raw_size else b''
    except lzf.LZFError as exc:
        raise DatasetError(f'{path}: binary_compressed PCD data corrupt: {exc}') from None
    # Field-major: all points' values of field 0, then field 1, ...
    cols, start = [], 0
    for dt, s, c in zip(hdr.column_dtypes(), hdr.sizes, hdr.counts, strict=True):
        nbytes = hdr.points * s * c
        cols.append(np.frombuffer(data, dtype=dt, count=hdr.points * c,
                                  offset=start).reshape(hdr.points, c).copy())
        start += nbytes
    return cols


def read_pcd(path: PathLike, drop_nan: bool = True) -> dict[str, np.ndarray]:
    """PCD file -> {field name: (N,) or (N, count) array, ..., 'xyz': (N, 3) float32}.

    Organized clouds (HEIGHT > 1) come back flattened in row-major order. With
    drop_nan, points whose x, y or z is not finite are removed from every field.
    Padding fields named '_' are left out. Raises DatasetError naming the file.
    """
    raw = read_bytes(path)
    hdr = _parse_header(raw, path)
    reader = {'ascii': _columns_ascii, 'binary': _columns_binary,
              'binary_compressed': _columns_compressed}[hdr.data]
    cols = reader(raw, hdr, path)
    fields = {name: (col[:, 0] if col.shape[1] == 1 else col)
              for name, col in zip(hdr.fields, cols, strict=True) if name != '_'}
    return with_xyz(path, fields, drop_nan)


def write_pcd(path: PathLike, fields: dict[str, np.ndarray], data: str = 'binary',
              width: int | None = None, height: int = 1) -> None:
    """Write a PCD v0.7 file. fields: name -> (N,) or (N, k) numeric arrays, in order.

    A key 'xyz' with an (N, 3) array is written as fields x, y, z. `data` is one of
    ascii, binary, binary_compressed; width x height must equal N (organized clouds).
    """
    if data not in _ENCODINGS:
        raise ValueError(f'data must be one of {_ENCODINGS}, got {data!r}')
    cols: dict[str, np.ndarray] = {}
    for name, arr in fields.items():
        arr = np.asarray(arr)
        if name == 'xyz':
            cols.update(x=arr[:, 0], y=arr[:, 1], z=arr[:, 2])
        else:
            cols[name] = arr
    n = len(next(iter(cols.values())))
    cols = {k: np.ascontiguousarray(v if v.ndim == 2 else v.reshape(n, 1))
            for k, v in cols.items()}
    width = n if width is None else width
    if width * height != n:
        raise ValueError(f'width {width} x height {height} != {n} points')
    kinds = {'f': 'F', 'i': 'I', 'u': 'U'}
    types = [kinds[v.dtype.kind] for v in cols.values()]
    sizes = [v.dtype.itemsize for v in cols.values()]
    counts = [v.shape[1] for v in cols.values()]
    header = ('# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n'
              f'FIELDS {" ".join(cols)}\nSIZE {" ".join(map(str, sizes))}\n'
              f'TYPE {" ".join(types)}\nCOUNT {" ".join(map(str, counts))}\n'
              f'WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\n'
              f'POINTS {n}\nDATA {data}\n').encode('ascii')
    le = [v.astype(v.dtype.newbyteorder('<')) for v in cols.values()]
    if data == 'ascii':
        body = '\n'.join(' '.join(repr(x.item()) for row in (c[i] for c in le) for x in row)
                         for i in range(n)).encode('ascii') + b'\n'
    elif data == 'binary':
        rec = np.empty(n, dtype=[(f'f{i}', c.dtype, (c.shape[1],)) for i, c in enumerate(le)])
        for i, c in enumerate(le):
            rec[f'f{i}'] = c
        body = rec.tobytes()
    else:
        plain = b''.join(c.tobytes() for c in le)  # field-major, as PCL writes it
        packed = lzf.compress(plain)
        body = struct.pack('<II', len(packed), len(plain)) + packed
    Path(path).write_bytes(header + body)
