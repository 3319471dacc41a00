"""The coarse coordinates of bank/search.py's int8 index: principal axes and int8 scales.

IndexBasis rotates vote-space rows onto the bank's leading principal axes (an orthogonal
rotation: dot products unchanged) and keeps the leading coordinates as int8 codes; `_project`
computes each row's coordinates independently of the rows beside it (pgn_project.c), so an
index's appended codes equal a fresh build's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

# Default coarse width: the fewest coordinates (a multiple of 32) holding this share of the
# bank's energy: 128 of 512 for issue 13's synthetic bank, 192 of 224 for the whitened
# sensor bank, 512 of 640 for the shipped (whitened) one (BENCHMARKS.md "Large banks").
COARSE_ENERGY = 0.9
# Rows used to find the principal axes (a sample: the rotation only steers the coarse
# pass, the rescoring is exact whatever it is).
_PCA_ROWS = 20_000
# Rows per block when quantizing or encoding many rows (bounds the float temporaries).
_BLOCK_ROWS = 8192


class IndexBasis:
    """The coarse pass's coordinates: the bank's leading principal axes, int8 scales.

    rotation (d, r) float32 orthonormal columns; scale (r,) float32 per coordinate (a
    coordinate's largest |value| over the rows it was fitted on maps to 127); energy: share
    of those rows' squared norms on the r coordinates; rows: how many rows it was fitted on.
    """

    def __init__(self, rotation: np.ndarray, scale: np.ndarray, energy: float, rows: int
                 ) -> None:
        self.rotation, self.scale, self.energy, self.rows = rotation, scale, energy, rows

    @classmethod
    def fit(cls, feats: np.ndarray, coarse_dims: int | None, lib: Any
            ) -> tuple['IndexBasis', np.ndarray]:
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
        scale = np.maximum(np.abs(z).max(axis=0), 1e-12) / 127.0          # (r,)
        return cls(rotation, scale, energy, n), z

    def quantize(self, z: np.ndarray) -> np.ndarray:
        """Coordinates (M, r) float32 -> int8 codes (M, r), saturated at +-127.

        In blocks of rows: a large bank's float temporaries stay small.
        """
        out = np.empty(z.shape, np.int8)
        for i in range(0, len(z), _BLOCK_ROWS):
            blk = z[i:i + _BLOCK_ROWS] / self.scale
            np.rint(blk, out=blk)
            out[i:i + _BLOCK_ROWS] = np.clip(blk, -127, 127, out=blk)
        return out

    def encode(self, feats: np.ndarray, lib: Any) -> np.ndarray:
        """Rows (M, d) float32 -> int8 codes (M, r); row by row the same in any batch."""
        if len(feats) <= _BLOCK_ROWS:
            return self.quantize(_project(feats, self.rotation, lib))
        return np.concatenate([self.encode(feats[i:i + _BLOCK_ROWS], lib)
                               for i in range(0, len(feats), _BLOCK_ROWS)])


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
