"""The coarse coordinates of bank/search.py's index: principal axes and integer scales.

IndexBasis rotates vote-space rows onto the bank's leading principal axes (an orthogonal
rotation: dot products unchanged) and keeps the leading coordinates as 4-bit (packed two a
byte, `pack_codes`) or 8-bit integer codes; `_project` computes each row's coordinates
independently of the rows beside it (pgn_project.c), so an index's appended codes equal a
fresh build's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

# Default coarse width: the fewest coordinates (a multiple of 32) holding this share of the
# bank's energy: 128 of 512 for issue 13's synthetic bank, 192 of 224 for the whitened
# sensor bank, 512 of 640 for the shipped (whitened) one (benchmarks/log "Large banks").
COARSE_ENERGY = 0.9
# Bits a coarse code: 4 (codes in [-7, 7], half the bytes of 8) or 8 ([-127, 127]). On the
# shipped scan section (288 of 320 dims) 4 bits kept 8 bits' fidelity against the exact
# search (0 of 9,843 train and 0 of 4,936 test labels differ), and its coarse pass after
# idle time takes 1.0-1.2 ms instead of 1.7-2.2 (benchmarks/log, "Third session of 2026-12-03").
COARSE_BITS = 4
_CODE_TOP = {4: 7, 8: 127}      # bits -> the largest |code|
# Rows used to find the principal axes (a sample: the rotation only steers the coarse
# pass, the rescoring is exact whatever it is).
_PCA_ROWS = 20_000
# Rows per block when quantizing or encoding many rows (bounds the float temporaries).
_BLOCK_ROWS = 8192


class IndexBasis:
    """The coarse pass's coordinates: the bank's leading principal axes, integer scales.

    rotation (d, r) float32 orthonormal columns; scale (r,) float32 per coordinate (a
    coordinate's largest |value| over the rows it was fitted on maps to the largest code,
    7 or 127); energy: share of those rows' squared norms on the r coordinates; rows: how
    many rows it was fitted on; bits: 4 or 8 a code.
    """

    def __init__(self, rotation: np.ndarray, scale: np.ndarray, energy: float, rows: int,
                 bits: int = COARSE_BITS) -> None:
        if bits not in _CODE_TOP:
            raise ValueError(f'coarse codes have 4 or 8 bits, got {bits}')
        self.rotation, self.scale, self.energy, self.rows = rotation, scale, energy, rows
        self.bits = bits

    @classmethod
    def fit(cls, feats: np.ndarray, coarse_dims: int | None, lib: Any,
            bits: int = COARSE_BITS) -> tuple['IndexBasis', np.ndarray]:
        """Fit on feats (N, d) float32 -> (basis, the rows' coordinates (N, r) float32)."""
        n, d = feats.shape
        # Principal axes of the (uncentred) second moment: they carry the most of every
        # dot product, so the leading coordinates approximate the cosines best.
        # In torch, on its thread budget (the node's torch_threads): numpy's BLAS threads
        # spin-wait on a loaded machine, which made a build cost several times its work.
        sample = torch.from_numpy(feats[::max(1, n // _PCA_ROWS)])
        evals, evecs = torch.linalg.eigh((sample.T @ sample).double())
        evals, evecs = evals.flip(0).clamp_min(0.0), evecs.flip(1)      # descending
        if coarse_dims is None:
            share = (evals.cumsum(0) / evals.sum().clamp_min(1e-30)).numpy()
            coarse_dims = 32 * (int(np.searchsorted(share, COARSE_ENERGY - 1e-9)) // 32 + 1)
        r = min(d, max(32, coarse_dims // 32 * 32))
        order = torch.arange(r)
        rotation = evecs[:, order].float().contiguous().numpy()          # (d, r)
        # share of the bank's squared norms on the coarse coordinates: the closer to 1,
        # the better the coarse pass ranks (issue 13's 512-d bank, 128 coords: 0.93)
        energy = float(evals[order].sum() / evals.sum().clamp_min(1e-30))
        z = _project(feats, rotation, lib)
        # The largest |value| by blocks of rows: a whole-bank np.abs(z) was a second (N, r)
        # float32 temporary at the node's start (90 MB on the shipped bank).
        top = np.zeros(r, np.float32)
        for i in range(0, n, _BLOCK_ROWS):
            np.maximum(top, np.abs(z[i:i + _BLOCK_ROWS]).max(axis=0), out=top)
        scale = np.maximum(top, 1e-12) / _CODE_TOP[bits]                     # (r,)
        return cls(rotation, scale, energy, n, bits), z

    @property
    def dims(self) -> int:
        return int(self.rotation.shape[1])

    def quantize(self, z: np.ndarray) -> np.ndarray:
        """Coordinates (M, r) float32 -> stored codes, saturated at the largest code.

        (M, r) int8 at 8 bits, (M, r / 2) uint8 (`pack_codes`) at 4. In blocks of rows: a
        large bank's float temporaries stay small.
        """
        top, r = _CODE_TOP[self.bits], z.shape[1]
        out = np.empty((len(z), r if self.bits == 8 else r // 2), np.int8 if self.bits == 8
                       else np.uint8)
        for i in range(0, len(z), _BLOCK_ROWS):
            blk = z[i:i + _BLOCK_ROWS] / self.scale
            np.rint(blk, out=blk)
            codes = np.clip(blk, -top, top, out=blk).astype(np.int8)
            out[i:i + _BLOCK_ROWS] = pack_codes(codes) if self.bits == 4 else codes
        return out

    def unpacked(self, codes: np.ndarray) -> np.ndarray:
        """Stored codes -> (M, r) int8 code values (no copy at 8 bits)."""
        return unpack_codes(codes, self.dims) if self.bits == 4 else codes

    def encode(self, feats: np.ndarray, lib: Any) -> np.ndarray:
        """Rows (M, d) float32 -> stored codes (see quantize); the same rows in any batch."""
        if len(feats) <= _BLOCK_ROWS:
            return self.quantize(_project(feats, self.rotation, lib))
        return np.concatenate([self.encode(feats[i:i + _BLOCK_ROWS], lib)
                               for i in range(0, len(feats), _BLOCK_ROWS)])


# Packed 4-bit rows, in chunks of up to 64 bytes: in a chunk of L bytes starting at byte
# b, byte b + t holds code 2b + t in its low 4 bits and code 2b + L + t in its high ones, each
# + 8. So a chunk's two halves meet contiguous slices of the query (core/kernels/pgn_scan4.c).
_PACK_CHUNK = 64


def pack_codes(codes: np.ndarray) -> np.ndarray:
    """(M, r) int8 codes in [-8, 7], r a multiple of 32 -> (M, r / 2) uint8 packed rows."""
    m, r = codes.shape
    if r % 32:
        raise ValueError(f'4-bit codes need a multiple of 32 a row, got {r}')
    u = (codes.astype(np.int16) + 8).astype(np.uint8)
    out, p = np.empty((m, r // 2), np.uint8), r // 2
    for b in range(0, p, _PACK_CHUNK):
        n = min(_PACK_CHUNK, p - b)
        out[:, b:b + n] = u[:, 2 * b:2 * b + n] | (u[:, 2 * b + n:2 * b + 2 * n] << 4)
    return out


def unpack_codes(packed: np.ndarray, dims: int) -> np.ndarray:
    """pack_codes's inverse: (M, dims / 2) uint8 -> (M, dims) int8."""
    out, p = np.empty((packed.shape[0], dims), np.int8), dims // 2
    for b in range(0, p, _PACK_CHUNK):
        n = min(_PACK_CHUNK, p - b)
        out[:, 2 * b:2 * b + n] = (packed[:, b:b + n] & 15).astype(np.int8) - 8
        out[:, 2 * b + n:2 * b + 2 * n] = (packed[:, b:b + n] >> 4).astype(np.int8) - 8
    return out


def _project(feats: np.ndarray, rotation: np.ndarray, lib: Any) -> np.ndarray:
    """Rows feats (N, d) @ rotation (d, r) -> (N, r) float32.

    With the C kernels each row's result does not depend on the others (pgn_project.c), so
    an index's appended codes equal a fresh build's; torch's GEMM otherwise.
    """
    if lib is None:
        return (torch.from_numpy(feats) @ torch.from_numpy(rotation)).numpy()
    feats = np.ascontiguousarray(feats, dtype=np.float32)
    out = np.empty((feats.shape[0], rotation.shape[1]), np.float32)
    lib.pgn_project_f32(feats.ctypes.data, feats.shape[0], feats.shape[1],
                        rotation.ctypes.data, rotation.shape[1], out.ctypes.data)
    return out
