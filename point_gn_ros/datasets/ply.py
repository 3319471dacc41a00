"""PLY reader: ascii, binary_little_endian, binary_big_endian; the vertex element's x y z."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from point_gn_ros.datasets._common import PathLike, read_bytes, with_xyz
from point_gn_ros.errors import DatasetError

_TYPES = {'char': 'i1', 'int8': 'i1', 'uchar': 'u1', 'uint8': 'u1',
          'short': 'i2', 'int16': 'i2', 'ushort': 'u2', 'uint16': 'u2',
          'int': 'i4', 'int32': 'i4', 'uint': 'u4', 'uint32': 'u4',
          'float': 'f4', 'float32': 'f4', 'double': 'f8', 'float64': 'f8'}
_FORMATS = {'ascii': '', 'binary_little_endian': '<', 'binary_big_endian': '>'}


@dataclass
class _Element:
    """One `element` block: name, count and (name, type, list count type or None)."""

    name: str
    count: int
    props: list[tuple[str, str, str | None]] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p[2] is not None for p in self.props)


def _parse_header(raw: bytes, path: PathLike) -> tuple[str, list[_Element], int]:
    """-> (format, elements, offset of the first data byte)."""
    if not raw.startswith(b'ply'):
        raise DatasetError(f'{path}: bad PLY header: file does not start with "ply"')
    end = raw.find(b'end_header')
    if end < 0:
        raise DatasetError(f'{path}: bad PLY header: no end_header line')
    nl = raw.find(b'\n', end)
    if nl < 0:
        raise DatasetError(f'{path}: bad PLY header: nothing after end_header')
    try:
        lines = raw[:end].decode('ascii').splitlines()[1:]
    except UnicodeDecodeError:
        raise DatasetError(f'{path}: bad PLY header: non-ASCII bytes') from None
    fmt = None
    elements: list[_Element] = []
    for line in lines:
        words = line.split()
        if not words or words[0] in ('comment', 'obj_info'):
            continue
        try:
            if words[0] == 'format':
                fmt = words[1]
                if fmt not in _FORMATS:
                    raise DatasetError(f'{path}: bad PLY header: unknown format {fmt!r}')
            elif words[0] == 'element':
                elements.append(_Element(words[1], int(words[2])))
            elif words[0] == 'property' and words[1] == 'list':
                elements[-1].props.append((words[4], _TYPES[words[3]], _TYPES[words[2]]))
            elif words[0] == 'property':
                elements[-1].props.append((words[2], _TYPES[words[1]], None))
            else:
                raise DatasetError(f'{path}: bad PLY header: unknown line {line!r}')
        except (IndexError, KeyError, ValueError):
            raise DatasetError(f'{path}: bad PLY header line {line!r}') from None
    if fmt is None:
        raise DatasetError(f'{path}: bad PLY header: no format line')
    return fmt, elements, nl + 1


def _skip_binary(raw: bytes, pos: int, el: _Element, order: str) -> int:
    """Offset just past a binary element that has list properties (walked row by row)."""
    for _ in range(el.count):
        for _name, typ, count_type in el.props:
            size = np.dtype(typ).itemsize
            if count_type is None:
                pos += size
            else:
                cdt = np.dtype(order + count_type)
                n = int(np.frombuffer(raw, dtype=cdt, count=1, offset=pos)[0])
                pos += cdt.itemsize + n * size
    return pos


def _vertex_binary(raw: bytes, fmt: str, elements: list[_Element], offset: int,
                   path: PathLike) -> dict[str, np.ndarray]:
    order = _FORMATS[fmt]
    pos = offset
    for el in elements:
        if el.has_lists:
            if el.name == 'vertex':
                raise DatasetError(f'{path}: PLY vertex element with list properties '
                                   'is not supported')
            try:
                pos = _skip_binary(raw, pos, el, order)
            except ValueError:
                raise DatasetError(f'{path}: binary PLY data truncated in element '
                                   f'{el.name!r}') from None
            continue
        dt = np.dtype([(name, order + typ) for name, typ, _ in el.props])
        if el.name != 'vertex':
            pos += el.count * dt.itemsize
            continue
        need = el.count * dt.itemsize
        if len(raw) - pos < need:
            raise DatasetError(f'{path}: binary PLY data truncated: {len(raw) - pos} bytes '
                               f'for {el.count} vertices x {dt.itemsize} bytes = {need}')
        rec = np.frombuffer(raw, dtype=dt, count=el.count, offset=pos)
        return {name: rec[name].astype(rec.dtype[name].newbyteorder('='))
                for name in rec.dtype.names}
    raise DatasetError(f'{path}: PLY file has no vertex element')


def _vertex_ascii(raw: bytes, elements: list[_Element], offset: int,
                  path: PathLike) -> dict[str, np.ndarray]:
    lines = raw[offset:].splitlines()
    row = 0
    for el in elements:
        if el.name != 'vertex':
            row += el.count  # one line per element instance
            continue
        if el.has_lists:
            raise DatasetError(f'{path}: PLY vertex element with list properties '
                               'is not supported')
        body = lines[row:row + el.count]
        if len(body) < el.count:
            raise DatasetError(f'{path}: ascii PLY data truncated: {len(body)} vertex lines, '
                               f'header says {el.count}')
        tokens = b' '.join(body).split()
        width = len(el.props)
        if len(tokens) != el.count * width:
            raise DatasetError(f'{path}: ascii PLY vertex lines have {len(tokens)} values, '
                               f'header says {el.count} x {width}')
        try:
            table = np.array(tokens, dtype=np.float64).reshape(el.count, width)
        except ValueError:
            raise DatasetError(f'{path}: ascii PLY vertex data has a non-numeric value') from None
        return {name: table[:, j].astype(typ) for j, (name, typ, _) in enumerate(el.props)}
    raise DatasetError(f'{path}: PLY file has no vertex element')


def read_ply(path: PathLike, drop_nan: bool = True) -> dict[str, np.ndarray]:
    """PLY file -> {vertex property: (N,) array, ..., 'xyz': (N, 3) float32}.

    Only the vertex element is returned (faces etc. are skipped). With drop_nan,
    vertices with a non-finite x, y or z are removed. Raises DatasetError naming
    the file.
    """
    raw = read_bytes(path)
    fmt, elements, offset = _parse_header(raw, path)
    if fmt == 'ascii':
        fields = _vertex_ascii(raw, elements, offset, path)
    else:
        fields = _vertex_binary(raw, fmt, elements, offset, path)
    return with_xyz(path, fields, drop_nan)
