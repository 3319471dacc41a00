"""Fast Point-GN encoder: the production path behind the oracle in encoder_naive.py.

Two back-ends compute the same function:

- 'kernel' (CPU default): fused C kernels (point_gn_ros/kernels), one cloud per
  call, never building an (S, k, D) tensor; FPS and kNN round distances exactly
  like the oracle, so neighbour choices are identical. Batches are split over
  worker threads (ctypes releases the GIL). Each cloud's result depends only on
  that cloud, so batch composition and thread count never change a bit.
- 'torch': plain batched torch ops, used for device='cuda' and as the CPU
  fallback when no C compiler is available. On CUDA it is untested here (no GPU
  on the development machine); reductions there may round differently, so
  near-tie FPS/kNN choices could differ from the CPU oracle.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
import logging
import os
import threading
import time
from typing import Literal

import numpy as np
import torch
from torch.nn import functional

from point_gn_ros.core import kernels
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.encoder_naive import gpe, gpe_centres
from point_gn_ros.core.threads import name_os_thread

Backend = Literal['auto', 'kernel', 'torch']
_log = logging.getLogger(__name__)
_DEFAULT_CFG = EncoderConfig()  # frozen dataclass: safe to share as a default


def default_threads() -> int:
    """Worker threads for batches: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


_spare: tuple[float, bool] = (-1e9, False)     # (when checked, result)


def spare_cpu() -> bool:
    """Whether a second CPU is likely free: the 1-minute load average leaves one spare.

    Checked at most once a second. What lets one piece of work take a second thread (a lone
    cloud here, a lone query's coarse pass in bank/index.py) without taking a core from
    other work on a busy machine.
    """
    global _spare
    now = time.monotonic()
    checked, spare = _spare
    if now - checked > 1.0:
        try:
            spare = default_threads() > 1 and os.getloadavg()[0] <= default_threads() - 1.0
        except OSError:  # no load average on this platform
            spare = False
        _spare = (now, spare)
    return spare


class PointGNEncoder:
    """Point-GN encoder agreeing with encoder_naive.NaiveEncoder (within 1e-4 relative).

    cfg: encoder hyper-parameters. device: 'cpu' or a torch device string ('cuda').
    backend: 'auto' (kernel on CPU if it builds, else torch), 'kernel' or 'torch'.
    threads: worker threads for batches on the kernel back-end (default: usable CPUs).
    lone_threads: threads for a batch of one cloud: 1, 2, or None (default) = 2 while
    the machine has a CPU to spare (see `_lone_threads`), else 1. Results are
    bit-identical either way.
    """

    def __init__(self, cfg: EncoderConfig = _DEFAULT_CFG, device: str = 'cpu',
                 backend: Backend = 'auto', threads: int | None = None,
                 lone_threads: int | None = None) -> None:
        cfg.require_single_scale()
        self.cfg = cfg
        self.device = torch.device(device)
        self.threads = max(1, int(threads or default_threads()))
        if lone_threads not in (None, 1, 2):
            raise ValueError(f'lone_threads must be None, 1 or 2, got {lone_threads!r}')
        self.lone_threads = lone_threads
        if backend not in ('auto', 'kernel', 'torch'):
            raise ValueError(f"backend must be 'auto', 'kernel' or 'torch', got {backend!r}")
        if backend == 'auto':
            backend = 'kernel' if self.device.type == 'cpu' and kernels.load() else 'torch'
            if self.device.type == 'cpu' and backend == 'torch':
                _log.warning('point_gn: compiled kernels unavailable (%s); using the torch '
                             'encoder, ~100x slower', kernels.last_error())
        elif backend == 'kernel':
            if self.device.type != 'cpu':
                raise ValueError('the kernel back-end runs on the CPU only')
            if kernels.load() is None:
                raise RuntimeError(f'compiled kernels unavailable: {kernels.last_error()}')
        self.backend: str = backend
        # Gaussian centres exactly as the oracle builds them (torch.linspace, float32):
        # init block, then one 2D_i/3 block per stage.
        blocks = [gpe_centres(cfg.init_dim)] + [gpe_centres(d) for d in cfg.stage_dims]
        self._centres = np.ascontiguousarray(torch.cat(blocks).numpy(), dtype=np.float32)
        self._pool: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()
        self.warmup_seconds: float | None = None
        self._chunks_per_worker = 4

    def __repr__(self) -> str:
        return (f'PointGNEncoder(backend={self.backend!r}, device={str(self.device)!r}, '
                f'threads={self.threads})')

    def warmup(self) -> float:
        """Run one small batch through everything (threads, first-touch memory): seconds taken.

        Construction already built or loaded the compiled kernels (about 1.5 s the first
        time on a machine, ~0.1 s from the disk cache); after warmup() no call pays a
        one-off cost.
        """
        t0 = time.perf_counter()
        gen = torch.Generator().manual_seed(0)
        cloud = torch.rand(max(2, self.threads), self.cfg.num_points, 3, generator=gen) - 0.5
        self.encode(cloud)
        self.warmup_seconds = time.perf_counter() - t0
        return self.warmup_seconds

    @torch.no_grad()
    def encode(self, xyz: torch.Tensor) -> torch.Tensor:
        """Encode prepared clouds: xyz (B, num_points, 3) float32 -> (B, feature_dim) float32 CPU.

        Clouds must already be resampled and normalised (sampling.prepare).
        """
        return self.encode_later(xyz, overlap=False)()

    @torch.no_grad()
    def encode_later(self, xyz: torch.Tensor, overlap: bool = True) -> Callable[[], torch.Tensor]:
        """`encode(xyz)` started now on the worker threads; the returned call waits for it.

        overlap: a batch of two or more clouds runs on the worker pool while the caller goes
        on (the node classifies the batch ahead meanwhile); otherwise, and for one cloud
        (which the caller shares with the helper thread, `_run_with_helper`), it is encoded
        before returning.
        The features are the same bits either way. Invalid clouds raise here.
        """
        xyz = torch.as_tensor(xyz)
        if xyz.ndim != 3 or xyz.shape[1] != self.cfg.num_points or xyz.shape[2] != 3:
            raise ValueError(f'expected clouds of shape (B, {self.cfg.num_points}, 3), '
                             f'got {tuple(xyz.shape)}')
        if xyz.shape[0] == 0:
            return _done(torch.zeros(0, self.cfg.feature_dim))
        if self.backend == 'kernel':
            # numpy, not torch, for the checks: a torch op on a large batch wakes torch's
            # OpenMP pool, whose spinning threads then steal the cores from the kernels.
            arr = np.ascontiguousarray(xyz.detach().cpu().numpy(), dtype=np.float32)
            if not np.isfinite(arr).all():
                raise ValueError('clouds contain NaN or infinite coordinates')
            return self._encode_kernel(arr, overlap)
        if not bool(torch.isfinite(xyz).all()):
            raise ValueError('clouds contain NaN or infinite coordinates')
        return _done(_encode_torch(xyz.to(self.device, torch.float32), self.cfg).cpu())

    # -- kernel back-end -------------------------------------------------------------------

    def _run_chunk(self, xyz: np.ndarray, out: np.ndarray) -> None:
        lib = kernels.load()
        assert lib is not None
        cfg = self.cfg
        rc = lib.pgn_encode(xyz.ctypes.data, xyz.shape[0], cfg.num_points, cfg.init_dim,
                            cfg.stages, cfg.k, cfg.sigma, self._centres.ctypes.data,
                            cfg.feature_dim, out.ctypes.data)
        if rc != 0:
            raise MemoryError('Point-GN kernel could not allocate its work space')

    def _lone_threads(self) -> int:
        """Threads for one cloud: 2 only while a second CPU is likely free.

        A helper thread that is not scheduled costs the lone cloud only its start (the
        caller takes its chunks), but on a busy machine it would take a core from other
        work: so 2 only when the 1-minute load average leaves a CPU spare (checked at
        most once a second).
        """
        if self.lone_threads is not None:
            return self.lone_threads
        if self.threads < 2:
            return 1
        return 2 if spare_cpu() else 1

    def _run_with_helper(self, xyz: np.ndarray, out: np.ndarray) -> None:
        lib = kernels.load()
        assert lib is not None
        cfg = self.cfg
        rc = lib.pgn_encode_with_helper(xyz.ctypes.data, cfg.num_points, cfg.init_dim, cfg.stages,
                                 cfg.k, cfg.sigma, self._centres.ctypes.data, cfg.feature_dim,
                                 out.ctypes.data)
        if rc != 0:
            raise MemoryError('Point-GN kernel could not allocate its work space')

    def _encode_kernel(self, arr: np.ndarray, overlap: bool = False
                       ) -> Callable[[], torch.Tensor]:
        """arr: (B, num_points, 3) float32 C-contiguous -> call giving (B, feature_dim)."""
        out = np.empty((arr.shape[0], self.cfg.feature_dim), dtype=np.float32)
        workers = min(self.threads, arr.shape[0])
        if arr.shape[0] == 1 and self._lone_threads() == 2:
            self._run_with_helper(arr, out)  # the caller and a helper share each stage
        elif workers == 1:
            self._run_chunk(arr, out)
        else:
            # A few chunks per worker, so that a worker slowed by other processes on a
            # shared machine does not hold up the batch: the others take its chunks.
            chunks = min(arr.shape[0], workers * self._chunks_per_worker)
            bounds = np.linspace(0, arr.shape[0], chunks + 1).round().astype(int)
            pool = self._get_pool()
            futures = [pool.submit(self._run_chunk, arr[a:b], out[a:b])
                       for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]

            def wait() -> torch.Tensor:
                for fut in futures:
                    fut.result()
                return torch.from_numpy(out)
            return wait if overlap else _done(wait())
        return _done(torch.from_numpy(out))

    def _get_pool(self) -> ThreadPoolExecutor:
        with self._pool_lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix='point_gn_enc',
                                                initializer=name_os_thread)
            return self._pool

    def close(self) -> None:
        """Stop the worker threads (they are idle between calls; this is tidiness)."""
        with self._pool_lock:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None

    def __del__(self) -> None:
        pool = getattr(self, '_pool', None)
        if pool is not None:
            pool.shutdown(wait=False)


def _done(features: torch.Tensor) -> Callable[[], torch.Tensor]:
    """An encode_later result that is already there."""
    return lambda: features


# -- torch back-end (any device) ---------------------------------------------------------------


def _sq_dist_batched(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Oracle's distance formula batched: a (B, M, 3), b (B, N, 3) -> (B, M, N)."""
    d = a[:, :, None, :] - b[:, None, :, :]
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def _fps_batched(xyz: torch.Tensor, m: int) -> torch.Tensor:
    """Oracle FPS for each cloud: xyz (B, N, 3) -> (B, m) int64."""
    bsz = xyz.shape[0]
    # Per-cloud means, exactly the oracle's op (a batched mean may round differently).
    centroid = torch.stack([c.mean(dim=0) for c in xyz])                  # (B, 3)
    cur = torch.argmax(_sq_dist_batched(xyz, centroid[:, None, :])[..., 0], dim=1)
    rows = torch.arange(bsz, device=xyz.device)
    idx = torch.empty(bsz, m, dtype=torch.int64, device=xyz.device)
    min_d = torch.full(xyz.shape[:2], float('inf'), dtype=xyz.dtype, device=xyz.device)
    for i in range(m):
        idx[:, i] = cur
        d = _sq_dist_batched(xyz, xyz[rows, cur][:, None, :])[..., 0]   # (B, N)
        min_d = torch.minimum(min_d, d)
        cur = torch.argmax(min_d, dim=1)  # first maximum, like the oracle
    return idx


def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Gather rows per cloud: x (B, N, C), idx (B, ...) -> (B, ..., C)."""
    bsz = x.shape[0]
    flat = idx.reshape(bsz, -1)
    out = torch.gather(x, 1, flat[..., None].expand(-1, -1, x.shape[-1]))
    return out.reshape(*idx.shape, x.shape[-1])


def _encode_torch_chunk(xyz: torch.Tensor, cfg: EncoderConfig) -> torch.Tensor:
    bsz = xyz.shape[0]
    feat = gpe(xyz, cfg.init_dim, cfg.sigma)                             # (B, N, D0)
    out = []
    for s in cfg.stage_points:
        k = min(cfg.k, xyz.shape[1])
        centre_idx = _fps_batched(xyz, s)                                # (B, S)
        cxyz, cfeat = _gather(xyz, centre_idx), _gather(feat, centre_idx)
        nb = torch.sort(_sq_dist_batched(cxyz, xyz), dim=2, stable=True).indices[..., :k]
        dxyz = _gather(xyz, nb) - cxyz[:, :, None, :]                    # (B, S, K, 3)
        dxyz = dxyz / (dxyz.reshape(bsz, -1).std(dim=1) + 1e-5)[:, None, None, None]
        dfeat = _gather(feat, nb) - cfeat[:, :, None, :]                 # (B, S, K, D)
        dfeat = dfeat / (dfeat.reshape(bsz, -1).std(dim=1) + 1e-5)[:, None, None, None]
        f = torch.cat([dfeat, cfeat[:, :, None, :].expand_as(dfeat)], dim=-1)
        pe = gpe(dxyz, f.shape[-1], cfg.sigma)
        w = (f + pe) * pe
        feat = functional.gelu(w.max(dim=2).values + w.mean(dim=2))              # (B, S, 2D)
        xyz = cxyz
        out += [feat.max(dim=1).values, feat.mean(dim=1)]
    return torch.cat(out, dim=1)


def _encode_torch(xyz: torch.Tensor, cfg: EncoderConfig) -> torch.Tensor:
    """Batched torch encoder: xyz (B, N, 3) -> (B, feature_dim); chunks bound the memory."""
    chunk = 32 if xyz.device.type == 'cuda' else 4  # (chunk, S, K, 2D) temporaries
    return torch.cat([_encode_torch_chunk(xyz[i:i + chunk], cfg)
                      for i in range(0, xyz.shape[0], chunk)])
