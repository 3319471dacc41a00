"""Enrollment on a shared ROS graph, over real DDS: off by default, bounded when on.

This test process plays the other peer on the domain: it tries to re-teach, forget and
save on a default node (all refused: answers and files unchanged), then, with enrollment
on, sends bad names, oversized clouds, a burst of service calls and a SIGINT under load.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from node_testing import (REPO, TEST_NUM_POINTS, Harness, NodeProcess, cloud_msg,
                          harness, latest_diagnostics, pick, reliable_qos, stamp, tiny_bank)
from test_enroll_node import Client

__all__ = ['harness', 'tiny_bank']  # fixtures, imported so that pytest finds them

TIMEOUT_S = 60.0


def _start(bank: Path, log: Path, name: str, **params) -> NodeProcess:
    return NodeProcess({'bank_path': str(bank), 'num_points': TEST_NUM_POINTS,
                        'input_topics': ['objects'], 'qos_reliability': 'reliable',
                        'qos_depth': 100, 'queue_size': 200, 'max_batch': 8, **params}, log,
                       node_name=name)


def _fqn(name: str) -> str:
    return f'/{name}'


class _Peer(Client):
    """test_enroll_node.Client for a node of another name, with a few more helpers."""

    def __init__(self, harness: Harness, node: NodeProcess, name: str,
                 enrolling: bool = True) -> None:
        super().__init__(harness, node, _fqn(name), enrolling)

    def enroll_diag(self) -> dict:
        return latest_diagnostics(self.diag, ': enrollment')

    def labels(self, clouds: list[np.ndarray], base: int) -> list[int]:
        return [int(a[0][0]) for a in self.classify(clouds, base)]


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else b'<dir>')
            for p in sorted(path.rglob('*'))}


def _graph(h: Harness, fqn: str) -> tuple[set[str], set[str]]:
    """(topics subscribed, services offered) by the node `fqn`, as the graph shows them."""
    ns, name = fqn.rsplit('/', 1)
    subs = {t for t, _ in h.node.get_subscriber_names_and_types_by_node(name, ns or '/')}
    srvs = {s for s, _ in h.node.get_service_names_and_types_by_node(name, ns or '/')}
    return subs, srvs


def _set_any(h: Harness, fqn: str, name: str, value: object) -> tuple[bool, str]:
    """Set a parameter of node `fqn` as any peer would -> (successful, reason)."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    req = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
    result = h.call(SetParameters, f'{fqn}/set_parameters', req, 10.0, resend_s=5.0).results[0]
    return result.successful, result.reason


def test_a_peer_cannot_change_a_default_node(harness: Harness, tiny_bank: Path,
                                            tmp_path: Path) -> None:
    """Re-teach airplane as chair, forget lamp, aim saves at a file and at new folders."""
    from sensor_msgs.msg import PointCloud2

    files = tmp_path / 'files'
    files.mkdir()
    (files / 'notes.txt').write_text('an operator file\n')
    before_files = _tree(tmp_path)
    name = 'pgn_guard_default'
    node = _start(tiny_bank, tmp_path / 'node.log', name)
    fqn = _fqn(name)
    p = None
    try:
        p = _Peer(harness, node, name, enrolling=False)
        p.wait_classes(lambda names: len(names) == 6)
        planes, _ = pick('test', ('airplane', 'lamp'), 4)
        queries = [c * 0.6 + 1.0 for c in planes]
        before = p.labels(queries, 100)
        subs, srvs = _graph(harness, fqn)
        assert not [t for t in subs if 'enroll' in t], subs
        assert not [s for s in srvs if s.rsplit('/', 1)[-1] in (
            'forget', 'save_bank', 'start_capture', 'stop_capture')], srvs
        # The attacks: the topics and services are not there, the save target is read-only.
        assert p.try_set_param('enroll_class', 'chair')[0]   # a plain string, inert
        for key, value in (('save_bank_path', str(files / 'notes.txt')),
                           ('save_bank_path', str(tmp_path / 'new' / 'dirs' / 'b.npz'))):
            ok, reason = p.try_set_param(key, value)
            assert not ok and 'read-only' in reason.lower(), reason
        # Nor can a peer change the answers through the live parameters (not enabled).
        for key, value in (('unknown_threshold', 0.99), ('top_k', 1)):
            ok, reason = _set_any(harness, fqn, key, value)
            assert not ok and 'read-only' in reason.lower(), reason
        pub = harness.node.create_publisher(PointCloud2, f'{fqn}/enroll_cloud',
                                            reliable_qos(100))
        for i in range(20):
            pub.publish(cloud_msg(queries[i % 4], 'base_link', stamp(7, i)))
        harness.spin_for(1.0)
        assert pub.get_subscription_count() == 0
        from std_srvs.srv import Trigger
        for srv in ('forget', 'save_bank'):
            client = harness.node.create_client(Trigger, f'{fqn}/{srv}')
            assert not client.wait_for_service(timeout_sec=1.0)
            harness.node.destroy_client(client)
        harness.node.destroy_publisher(pub)
        assert p.labels(queries, 200) == before
        assert p.classes() == ['airplane', 'bottle', 'chair', 'guitar', 'lamp', 'table']
        assert harness.spin_until(lambda: p.enroll_diag().get('_message', '').startswith('off'),
                                  10.0), p.enroll_diag()
    finally:
        if p is not None:
            p.close()
        assert node.stop() == 0, node.log()
    assert _tree(tmp_path) == {**before_files, 'node.log': _tree(tmp_path)['node.log']}
    assert 'enrollment is off' in node.log()


_KILLED_SAVER = """
import sys, time
import numpy as np
from point_gn_ros.bank.enroll import BankFile, save_atomic
bf = BankFile.load(sys.argv[1])
real = np.savez_compressed
def slow(f, **arrays):
    real(f, **arrays)
    print('writing', flush=True)
    time.sleep(60)
np.savez_compressed = slow
save_atomic(bf, sys.argv[2])
"""


def _killed_save(bank: Path, target: Path) -> list[str]:
    """A process saving to `target`, killed by SIGKILL mid-write -> the temp files it left."""
    proc = subprocess.Popen([sys.executable, '-c', _KILLED_SAVER, str(bank), str(target)],
                            env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline().strip() == b'writing'
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    return sorted(p.name for p in target.parent.glob('.*'))


def test_saves_go_where_the_operator_said_and_always_load(harness: Harness, tiny_bank: Path,
                                                         tmp_path: Path) -> None:
    """A save folder: names confined to it; bad names and huge clouds refused and counted.

    Temp files of a save killed before the node started are gone once it has started.
    """
    from point_gn_ros.bank.store import FeatureBank

    saves = tmp_path / 'saves'
    saves.mkdir()
    left = _killed_save(tiny_bank, saves / 'bank.npz')
    assert left and all('.tmp.npz' in n for n in left), left
    name = 'pgn_guard_saves'
    node = _start(tiny_bank, tmp_path / 'node.log', name, enable_enrollment=True,
                  save_bank_path=str(saves), enroll_class='sofa', max_points_per_message=5000)
    p = None
    try:
        p = _Peer(harness, node, name)
        p.wait_classes(lambda names: len(names) == 6)
        assert sorted(x.name for x in saves.iterdir()) == [], 'stale temp files kept'
        assert 'left by an interrupted save' in node.log()
        ok, reason = p.try_set_param('save_bank_path', str(tmp_path / 'elsewhere'))
        assert not ok and 'read-only' in reason.lower()
        sofa, _ = pick('test', ('sofa',), 3)
        for i, cloud in enumerate(sofa):
            p.pub_cloud.publish(cloud_msg(cloud * 0.5 + 2.0, 'base_link', stamp(9, i)))
        p.wait_classes(lambda names: 'sofa' in names)
        # Names the loader would refuse, and a cloud over max_points_per_message.
        for bad in ('chair\rtable', 'k' * 10_000):
            p.set_param('enroll_class', bad)
            p.pub_cloud.publish(cloud_msg(sofa[0], 'base_link', stamp(10, 0)))
        big = np.random.default_rng(0).normal(size=(6000, 3)).astype(np.float32)
        p.set_param('enroll_class', 'sofa')
        p.pub_cloud.publish(cloud_msg(big, 'base_link', stamp(11, 0)))
        assert harness.spin_until(lambda: p.enroll_diag().get('enroll_refused.class_name') == '2'
                                  and p.enroll_diag().get('enroll_refused.too_many_points') == '1',
                                  20.0), (p.enroll_diag(), node.log())
        # Save names: confined to the folder, no new folders, no hidden files.
        for bad in ('../escape.npz', '/tmp/abs.npz', 'new/dir.npz', '.hidden.npz', 'b.txt'):
            p.set_param('save_bank_name', bad)
            ok, text = p.call('save_bank')
            assert not ok and 'save_bank_name' in text, (bad, text)
        p.set_param('save_bank_name', 'taught.npz')
        ok, text = p.call('save_bank')
        assert ok, text
        assert sorted(x.name for x in saves.iterdir()) == ['taught.npz']
        assert sorted(x.name for x in tmp_path.iterdir()) == ['node.log', 'saves']
        back = FeatureBank.load(saves / 'taught.npz')
        assert back.class_names[-1] == 'sofa' and back.num_classes == 7
    finally:
        if p is not None:
            p.close()
        assert node.stop() == 0, node.log()
    assert 'Traceback' not in node.log()


def test_thirty_concurrent_service_calls_are_all_answered(harness: Harness, tiny_bank: Path,
                                                          tmp_path: Path) -> None:
    from std_srvs.srv import Trigger

    name = 'pgn_guard_calls'
    node = _start(tiny_bank, tmp_path / 'node.log', name, enable_enrollment=True,
                  save_bank_path=str(tmp_path / 'b.npz'))
    fqn = _fqn(name)
    clients = []
    try:
        # Each client's reader may see every reply of the service's writer (DDS filters by
        # request id after the history): room for all 30, so this side loses none.
        qos = reliable_qos(64)
        clients = [harness.node.create_client(Trigger, f'{fqn}/save_bank', qos_profile=qos)
                   for _ in range(30)]
        assert all(c.wait_for_service(timeout_sec=TIMEOUT_S) for c in clients), node.log()
        for c in clients:               # each client's reply reader matched (node_testing)
            _answered_once(harness, c, Trigger.Request())
        futures = [c.call_async(Trigger.Request()) for c in clients]
        assert harness.spin_until(lambda: all(f.done() for f in futures), TIMEOUT_S), (
            f'{sum(f.done() for f in futures)} of 30 answered\n{node.log()}')
        answers = [f.result() for f in futures]
        done = [a for a in answers if a.success]
        busy = [a for a in answers if not a.success]
        assert done and all('busy' in a.message for a in busy), [a.message for a in answers]
        print(f'30 concurrent ~/save_bank calls: {len(done)} saved, {len(busy)} busy')
    finally:
        for c in clients:
            harness.node.destroy_client(c)
        assert node.stop() == 0, node.log()


def _answered_once(h: Harness, client, request) -> None:  # noqa: ANN001
    """Until one call of `client` is answered (sent again every 2 s).

    Then the server's reply writer has matched this client: a response sent before that is
    dropped (ros2/ros2#1253, see node_testing.Harness.call).
    """
    end = time.monotonic() + TIMEOUT_S
    while time.monotonic() < end:
        fut = client.call_async(request)
        if h.spin_until(fut.done, 2.0):
            return
        client.remove_pending_request(fut)
    raise AssertionError('a client was never answered')


def test_sigint_with_600_pending_examples_exits_within_2_s(harness: Harness, tiny_bank: Path,
                                                           tmp_path: Path) -> None:
    """600 examples in flight (slow commits: CV refits, 8 frames each); SIGINT: out in < 2 s."""
    name = 'pgn_guard_sigint'
    node = _start(tiny_bank, tmp_path / 'node.log', name, enable_enrollment=True,
                  enroll_class='sofa', enroll_max_pending=1000, enroll_augment='d4',
                  enroll_refit_gamma='cv', enroll_max_examples=50)
    p = None
    try:
        p = _Peer(harness, node, name)
        p.wait_classes(lambda names: len(names) == 6)
        sofa, _ = pick('test', ('sofa',), 20)
        for i in range(600):
            p.pub_cloud.publish(cloud_msg(sofa[i % 20] + np.float32(0.001 * i), 'base_link',
                                          stamp(20, i)))
            if i % 50 == 0:
                harness.spin_for(0.01)

        def pending() -> int:
            return int(p.enroll_diag().get('enroll_pending', 0))
        assert harness.spin_until(lambda: pending() > 100, 30.0), (p.enroll_diag(), node.log())
        diag = p.enroll_diag()
        total = sum(int(diag[k]) for k in ('enroll_pending', 'enroll_enrolled',
                                           'enroll_refused'))
        assert total <= 600, diag                     # counted honestly: never more than sent
    finally:
        if p is not None:
            p.close()
    t0 = time.monotonic()
    node.proc.send_signal(signal.SIGINT)
    code = node.wait(30)
    took = time.monotonic() - t0
    log = node.log()
    print(f'SIGINT with {pending_at(diag)} pending examples: exited in {took:.2f} s')
    assert code == 0 and took < 2.0, (took, log)
    assert 'pending example(s) of 1 class(es) dropped' in log, log
    assert 'Traceback' not in log and 'InvalidHandle' not in log and 'failed' not in log, log


def pending_at(diag: dict) -> str:
    return diag.get('enroll_pending', '?')


@pytest.fixture(autouse=True)
def _ros_extras() -> None:
    from node_testing import require_ros_extras
    require_ros_extras('std_srvs.srv')
