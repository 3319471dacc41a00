"""Classifier node start-up failures: one clear fatal line, exit code != 0, within seconds."""

from __future__ import annotations

from pathlib import Path
import time

from node_testing import TEST_NUM_POINTS, NodeProcess, tiny_bank

__all__ = ['tiny_bank']  # fixture, imported so that pytest finds it

START_TIMEOUT_S = 45.0   # generous: torch import on 2 busy cores


def _corrupt_banks(tmp: Path, good: Path) -> dict[str, Path]:
    garbage = tmp / 'garbage.npz'
    garbage.write_bytes(b'this is not a zip file at all' * 10)
    truncated = tmp / 'truncated.npz'
    truncated.write_bytes(good.read_bytes()[:200])
    return {'garbage': garbage, 'truncated': truncated}


def test_bad_start_fails_fast_with_one_clear_line(tiny_bank: Path, tmp_path: Path) -> None:
    cases = {
        'missing': ({'bank_path': str(tmp_path / 'nope.npz')}, 'bank file not found'),
        'mismatch': ({'bank_path': str(tiny_bank), 'num_points': 1024}, 'num_points'),
        'bad_choice': ({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                        'resample': 'bilinear'}, 'resample'),
        'out_of_range': ({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                          'max_batch': 0}, 'max_batch'),
    }
    import torch
    if not torch.cuda.is_available():
        cases['no_cuda'] = ({'bank_path': str(tiny_bank), 'num_points': TEST_NUM_POINTS,
                             'device': 'cuda'}, 'CUDA is not available')
    for name, path in _corrupt_banks(tmp_path, tiny_bank).items():
        cases[name] = ({'bank_path': str(path), 'num_points': TEST_NUM_POINTS}, str(path))
    # All at once: each pays the torch import, the machine has spare time while they wait.
    t0 = time.monotonic()
    procs = {name: NodeProcess(params, tmp_path / f'{name}.log')
             for name, (params, _) in cases.items()}
    try:
        for name, proc in procs.items():
            rc = proc.wait(START_TIMEOUT_S)
            log = proc.log()
            assert rc not in (0, None), f'{name}: exit {rc}\n{log}'
            fatal = [ln for ln in log.splitlines() if '[FATAL]' in ln]
            assert len(fatal) == 1, f'{name}:\n{log}'
            assert cases[name][1] in fatal[0], f'{name}: {fatal[0]}'
            assert 'Traceback' not in log, f'{name}:\n{log}'
    finally:
        for proc in procs.values():
            proc.stop(timeout=5)
    assert time.monotonic() - t0 < START_TIMEOUT_S


def test_managed_configure_failure_is_reported_and_the_node_stays(tmp_path: Path) -> None:
    """autostart:=false: a bad bank fails the configure transition with the reason."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    from node_testing import Harness

    fqn = '/managed_failure_classifier'
    proc = NodeProcess({'bank_path': str(tmp_path / 'nope.npz'), 'autostart': False},
                       tmp_path / 'managed.log', node_name=fqn[1:])
    harness = Harness('managed_failure_test')
    try:
        req = ChangeState.Request(transition=Transition(label='configure'))
        assert not harness.call(ChangeState, f'{fqn}/change_state', req, 60.0).success
        state = harness.call(GetState, f'{fqn}/get_state', GetState.Request(), resend_s=5.0)
        assert state.current_state.label == 'unconfigured'
        assert proc.proc.poll() is None
        assert 'configure failed: ' in proc.log() and 'bank file not found' in proc.log()
    finally:
        harness.close()
        assert proc.stop() == 0
    assert '[FATAL]' not in proc.log() and 'Traceback' not in proc.log()
