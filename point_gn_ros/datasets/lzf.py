"""LZF (liblzf) decompression and a simple compressor, in pure Python.

PCD `binary_compressed` payloads are LZF streams. The format is a sequence of
tokens: a control byte `c < 32` starts a literal run of `c + 1` bytes; otherwise
`c >> 5` is a back-reference length (7 = "read one more length byte") and the
low 5 bits plus the next byte give the distance back into the output.
"""

from __future__ import annotations


class LZFError(ValueError):
    """The stream is corrupt or does not decompress to the expected size."""


def decompress(data: bytes | bytearray | memoryview, expected_size: int) -> bytes:
    """LZF stream -> exactly `expected_size` bytes, or LZFError.

    Copies whole literal runs and back-references as slices, so the Python loop
    runs once per token rather than once per byte.
    """
    src = bytes(data)
    n_in = len(src)
    out = bytearray()
    ip = 0
    while ip < n_in:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            run = ctrl + 1
            if ip + run > n_in:
                raise LZFError(f'literal run of {run} bytes runs past the end of the input')
            out += src[ip:ip + run]
            ip += run
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    raise LZFError('back-reference length byte missing at the end of the input')
                length += src[ip]
                ip += 1
            if ip >= n_in:
                raise LZFError('back-reference offset byte missing at the end of the input')
            dist = ((ctrl & 0x1F) << 8) + src[ip] + 1
            ip += 1
            length += 2
            start = len(out) - dist
            if start < 0:
                raise LZFError(f'back-reference {dist} bytes back, before the start of the output')
            if dist >= length:
                out += out[start:start + length]
            else:
                # Overlapping copy repeats the last `dist` bytes (run-length style).
                pattern = bytes(out[start:])
                reps = -(-length // dist)
                out += (pattern * reps)[:length]
        if len(out) > expected_size:
            raise LZFError(f'decompresses to more than the expected {expected_size} bytes')
    if len(out) != expected_size:
        raise LZFError(f'decompressed to {len(out)} bytes, expected {expected_size}')
    return bytes(out)


def compress(data: bytes | bytearray | memoryview) -> bytes:
    """Bytes -> an LZF stream that `decompress` (and liblzf) accepts.

    Greedy matching with a 3-byte hash table, like liblzf but simpler; meant for
    writing test files and small clouds, not for speed.
    """
    src = bytes(data)
    n = len(src)
    out = bytearray()
    literals = bytearray()
    table: dict[bytes, int] = {}

    def flush() -> None:
        if literals:
            out.append(len(literals) - 1)
            out.extend(literals)
            literals.clear()

    i = 0
    while i < n:
        ref = -1
        if i + 2 < n:
            key = src[i:i + 3]
            ref = table.get(key, -1)
            table[key] = i
        if ref >= 0 and i - ref - 1 < 8192:
            max_len = min(264, n - i)
            length = 3
            while length < max_len and src[ref + length] == src[i + length]:
                length += 1
            flush()
            dist = i - ref - 1
            code = length - 2
            if code < 7:
                out.append((code << 5) | (dist >> 8))
            else:
                out.append((7 << 5) | (dist >> 8))
                out.append(code - 7)
            out.append(dist & 0xFF)
            i += length
        else:
            literals.append(src[i])
            if len(literals) == 32:
                flush()
            i += 1
    flush()
    return bytes(out)
