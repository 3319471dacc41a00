"""Every save that succeeds loads; bank files are read with bounds (no ROS).

Class names share one rule at enrollment and at load, the enrollment history is capped,
temporary files never outlive a failed or killed save, and a bank file cannot make a
reader allocate or decompress more than its limit.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
import zipfile
import zlib

import numpy as np
import pytest
import torch

from point_gn_ros.bank import enroll as enroll_mod
from point_gn_ros.bank.enroll import BankFile, EnrollError, MAX_HISTORY, add_examples, save_atomic
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.store import BANK_MAX_BYTES
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.bank.store import MAX_CLASS_NAME, check_class_names
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError

REPO = Path(__file__).resolve().parents[2]
D = EncoderConfig().feature_dim


def _bank(classes: int = 4, per_class: int = 5) -> BankFile:
    g = torch.Generator().manual_seed(0)
    centres = torch.randn(classes, D, generator=g)
    labels = torch.arange(classes).repeat_interleave(per_class)
    feats = centres[labels] + 0.3 * torch.randn(len(labels), D, generator=g)
    tf = FeatureTransform.fit(feats, 'none')
    bank = FeatureBank(features=tf(feats), labels=labels,
                       class_names=[f'c{i}' for i in range(classes)], config=EncoderConfig(),
                       transform=tf, gamma=50.0)
    return BankFile.of(bank, 'float16')


def _one(seed: int) -> torch.Tensor:
    return torch.randn(1, D, generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------ class names


@pytest.mark.parametrize('name', ['chair\rtable', 'x' * 10_000, 'a\nb', '   '])
def test_a_name_the_loader_refuses_is_refused_at_enrollment(name: str) -> None:
    """The same rule (and words) at enrollment as at load: no save can hold such a name."""
    with pytest.raises(EnrollError) as info:
        add_examples(_bank(), _one(1), name)
    assert str(info.value) == check_class_names(['ok', name.strip()])
    assert 'single lines' in str(info.value) and len(str(info.value)) < 300


@pytest.mark.parametrize('name', ['stuhl_\u00fc\u4e2d', '..', 'a/b/../c', '\x1b[31mred\x1b[0m',
                                  'y' * MAX_CLASS_NAME])
def test_odd_but_valid_names_enroll_save_and_load(name: str, tmp_path: Path) -> None:
    res = add_examples(_bank(), _one(2), name)
    back = FeatureBank.load(save_atomic(res.file, tmp_path / 'b.npz'))
    assert back.class_names[-1] == name


def test_a_save_that_would_not_load_is_refused_and_leaves_nothing(tmp_path: Path) -> None:
    """The metadata checks of load run before a save writes (belt and braces)."""
    bf = _bank()
    bad = BankFile(FeatureBank(**{**bf.bank.__dict__, 'class_names':
                                  ['c0', 'c1', 'c2', 'c3\r']}), bf.stored)
    with pytest.raises(ValueError, match='not saved: class names'):
        save_atomic(bad, tmp_path / 'b.npz')
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ history


def test_2200_enrollments_then_save_and_load(tmp_path: Path) -> None:
    """2,200 enrollments of long-named classes: the history is capped, the save loads.

    Unbounded, the history of these enrollments is > 1 MB of metadata: refused at load.
    """
    names = [f'{i}' * MAX_CLASS_NAME for i in range(4)]       # 256-character names
    source = 'capture of 200 object(s), 17 more over capture_max; 5 views fused into 9 more'
    bf = _bank()
    policy = RefitPolicy(gamma='keep')
    for i in range(2200):
        bf = add_examples(bf, _one(i), names[i % 4], source, policy).file
    meta = bf.bank.meta
    assert meta['bank_version'] == 2200
    assert len(bf.bank.enrollments) == MAX_HISTORY
    assert bf.bank.enrollments_compacted == 2200 - MAX_HISTORY
    assert bf.bank.enrollments[-1].version == 2200
    back = FeatureBank.load(save_atomic(bf, tmp_path / 'b.npz'))
    assert len(back) == 20 + 2200 and back.meta['bank_version'] == 2200
    assert len(json.dumps(back.meta)) < 500_000


# ------------------------------------------------------------------------------ temp files


def _failing_savez(written: int):  # noqa: ANN202
    """np.savez_compressed that writes `written` bytes, then fails as a full disk does."""
    def savez(f, **arrays) -> None:  # noqa: ANN001, ANN003
        f.write(b'\0' * written)
        raise OSError(errno.ENOSPC, 'No space left on device')
    return savez


def test_a_full_disk_leaves_no_temp_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                         ) -> None:
    bf = _bank()
    target = save_atomic(bf, tmp_path / 'bank.npz')
    before = target.read_bytes()
    monkeypatch.setattr(np, 'savez_compressed', _failing_savez(1 << 20))
    with pytest.raises(OSError, match='No space left'):
        save_atomic(add_examples(bf, _one(3), 'sofa').file, target)
    with pytest.raises(OSError, match='No space left'):
        bf.bank.save(tmp_path / 'plain.npz')                 # FeatureBank.save alone too
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bank.npz']
    assert target.read_bytes() == before


_SAVER = """
import sys, time
import numpy as np
from point_gn_ros.bank.enroll import BankFile, save_atomic
bf = BankFile.load(sys.argv[1])
real = np.savez_compressed
def slow(f, **arrays):
    real(f, **arrays)
    print('writing', flush=True)
    time.sleep(60)                     # killed here: both temp files exist
np.savez_compressed = slow
save_atomic(bf, sys.argv[2])
"""


def test_temp_files_of_a_killed_save_are_removed_by_the_next(tmp_path: Path) -> None:
    bf = _bank()
    src = save_atomic(bf, tmp_path / 'src.npz')
    target = tmp_path / 'out' / 'bank.npz'
    target.parent.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, '-c', _SAVER, str(src), str(target)], env=env,
                            stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline().strip() == b'writing'
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    left = sorted(p.name for p in target.parent.iterdir())
    assert left and all(n.startswith('.bank.npz.') and '.tmp.npz' in n for n in left), left
    save_atomic(bf, target)
    assert sorted(p.name for p in target.parent.iterdir()) == ['bank.npz']


def test_the_temp_file_of_a_live_saver_is_kept(tmp_path: Path) -> None:
    from point_gn_ros.bank.enroll import remove_stale_temps
    target = tmp_path / 'bank.npz'
    mine = tmp_path / f'.bank.npz.{os.getpid()}.7f.tmp.npz'
    other = tmp_path / f'.bank.npz.{os.getppid()}.7f.tmp.npz'   # a live process's
    unrelated = tmp_path / '.other.npz.1.7f.tmp.npz'
    for p in (mine, other, unrelated):
        p.write_bytes(b'x')
    assert remove_stale_temps(target) == [mine]
    assert other.exists() and unrelated.exists()


# ------------------------------------------------------------------------------ bounded reads


def _npy_header(shape: tuple[int, ...], dtype: str = '<f4') -> bytes:
    import io
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {'descr': dtype, 'fortran_order': False, 'shape': shape})
    return buf.getvalue()


def _lying_bank(path: Path, good: Path, member: str, raw: bytes) -> Path:
    """A copy of bank `good` whose `member` is replaced by raw .npy bytes."""
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(path, 'w', zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            data = raw if info.filename == member else src.read(info)
            dst.writestr(info.filename, data)
    return path


def _load_line(path: Path) -> tuple[int, str, float]:
    """`point_gn bank info PATH` in a child: (exit code, output, seconds)."""
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, '-m', 'point_gn_ros.cli', 'bank', 'info', str(path)],
                         capture_output=True, text=True, env=dict(os.environ,
                                                                   PYTHONPATH=str(REPO)),
                         timeout=120)
    return out.returncode, out.stdout + out.stderr, time.monotonic() - t0


def test_a_lying_npy_header_gives_one_line(tmp_path: Path) -> None:
    good = save_atomic(_bank(), tmp_path / 'good.npz')
    raw = _npy_header((10**12, 256)) + b'\0' * 4096
    bad = _lying_bank(tmp_path / 'liar.npz', good, 'features.npy', raw)
    with pytest.raises(BankError, match=r'features.npy: header says \(1000000000000, 256\)'):
        FeatureBank.load(bad)
    code, out, _ = _load_line(bad)
    assert code == 2 and 'Traceback' not in out and 'MemoryError' not in out, out
    assert len([line for line in out.splitlines() if line.strip()]) == 1, out
    assert 'header says' in out


_MEASURE = """
import resource, sys, time
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.errors import BankError
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.monotonic()
try:
    FeatureBank.load(sys.argv[1])
    print('loaded')
except BankError as exc:
    print(f'refused {time.monotonic() - t0:.3f} '
          f'{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before} {exc}')
"""


class _RepeatingDeflate:
    """A raw deflate compressor that compresses `chunk` once and repeats its output.

    Each piece ends with a full flush (byte-aligned, no reference to earlier data), so the
    pieces concatenate into one valid deflate stream; zipfile still computes the real CRC.
    """

    def __init__(self, chunk: bytes) -> None:
        self.chunk = chunk
        self.block = self._piece(chunk)

    @staticmethod
    def _piece(data: bytes) -> bytes:
        c = zlib.compressobj(1, zlib.DEFLATED, -15)
        return c.compress(data) + c.flush(zlib.Z_FULL_FLUSH)

    def compress(self, data: bytes) -> bytes:
        return self.block if data is self.chunk else self._piece(data)

    def flush(self) -> bytes:
        return zlib.compressobj(1, zlib.DEFLATED, -15).flush()


def test_a_zip_bomb_is_refused_before_it_is_decompressed(tmp_path: Path) -> None:
    """1.5 GB of zero features in a ~1.5 MB file: refused in < 1 s and < 100 MB of RSS."""
    good = save_atomic(_bank(), tmp_path / 'good.npz')
    rows = 1_500_000_000 // (4 * 256)
    bomb = tmp_path / 'bomb.npz'
    zero = bytes(1 << 22)
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(bomb, 'w', zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            if info.filename != 'features.npy':
                dst.writestr(info.filename, src.read(info))
        with dst.open('features.npy', 'w', force_zip64=True) as f:   # streamed: no 1.5 GB
            f._compressor = _RepeatingDeflate(zero)   # noqa: SLF001 - zlib once, not 360x
            f.write(_npy_header((rows, 256)))
            left = rows * 256 * 4
            while left:
                f.write(zero if left >= len(zero) else zero[:left])
                left -= min(left, len(zero))
    assert bomb.stat().st_size < 20_000_000
    out = subprocess.run([sys.executable, '-c', _MEASURE, str(bomb)], capture_output=True,
                         text=True, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=120)
    assert out.stdout.startswith('refused'), out.stdout + out.stderr
    _, seconds, rss_kb, *words = out.stdout.split()
    print(f'zip bomb refused in {float(seconds):.3f} s, +{int(rss_kb) / 1024:.1f} MB RSS: '
          f'{" ".join(words)}')
    assert float(seconds) < 1.0 and int(rss_kb) < 100 * 1024
    assert f'limit of {BANK_MAX_BYTES:,}' in out.stdout
    code, text, _ = _load_line(bomb)
    assert code == 2 and 'Traceback' not in text and len(text.strip().splitlines()) == 1, text


def test_a_member_larger_than_its_directory_entry_is_not_read_past_it(tmp_path: Path) -> None:
    """The header must match the member's stated size exactly: a short member is refused."""
    good = save_atomic(_bank(), tmp_path / 'good.npz')
    raw = _npy_header((20, D)) + b'\0' * 100        # claims 20 x D float32, holds 100 bytes
    bad = _lying_bank(tmp_path / 'short.npz', good, 'features.npy', raw)
    with pytest.raises(BankError, match='the member holds 100'):
        FeatureBank.load(bad)


def test_enrollment_module_keeps_its_cap_documented() -> None:
    assert str(MAX_HISTORY) in enroll_mod.__doc__
