"""The package builds with colcon and its installed executables run, as `ros2 run` would."""

import os
from pathlib import Path
import shutil
import subprocess
import sys

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    colcon = Path(sys.executable).parent / 'colcon'
    if not colcon.exists():
        pytest.fail('colcon is not installed in this environment (make installs it)')
    ws = tmp_path_factory.mktemp('ws')
    src = ws / 'src' / 'point_gn_ros'
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', '__pycache__', '*.egg-info', 'cache', 'runs',
        '.pytest_cache', '.hypothesis'))
    env = dict(os.environ, PATH=f'{colcon.parent}:{os.environ["PATH"]}')
    proc = subprocess.run([str(colcon), 'build', '--base-paths', 'src'], cwd=ws, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return ws / 'install'


def _run_installed(install: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = f'. {install}/setup.sh && {" ".join(args)}'
    return subprocess.run(['bash', '-c', cmd], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, PATH=f'{Path(sys.executable).parent}:'
                                                    f'{os.environ["PATH"]}'))


def test_installed_point_gn_runs(colcon_install: Path) -> None:
    exe = colcon_install / 'point_gn_ros' / 'lib' / 'point_gn_ros' / 'point_gn'
    assert exe.is_file()
    proc = _run_installed(colcon_install, str(exe), '--help')
    assert proc.returncode == 0, proc.stderr
    assert 'bank' in proc.stdout and 'eval' in proc.stdout


def test_install_layout_for_ros2_run(colcon_install: Path) -> None:
    share = colcon_install / 'point_gn_ros' / 'share'
    assert (colcon_install / 'point_gn_ros' / 'lib' / 'point_gn_ros' / 'classifier_node').is_file()
    assert (share / 'ament_index' / 'resource_index' / 'packages' / 'point_gn_ros').is_file()
    assert (share / 'point_gn_ros' / 'package.xml').is_file()
    assert (share / 'point_gn_ros' / 'config' / 'classifier.yaml').is_file()


def _installed_env(install: Path) -> dict[str, str]:
    """The environment `. install/setup.sh` gives, as `ros2 run` would see it."""
    out = _run_installed(install, 'env', '-0').stdout
    return dict(item.split('=', 1) for item in out.split('\0') if '=' in item)


def test_installed_classifier_node_answers_over_dds(colcon_install: Path, small_bank_path: Path,
                                                    tmp_path: Path) -> None:
    from conftest import load_modelnet_subset
    from node_testing import (Harness, NodeProcess, assert_same_labels, cloud_msg,
                              reliable_qos, stamp, stamp_key, to_sensor_frame)
    from sensor_msgs.msg import PointCloud2

    exe = colcon_install / 'point_gn_ros' / 'lib' / 'point_gn_ros' / 'classifier_node'
    env = _installed_env(colcon_install)
    node = NodeProcess({'bank_path': str(small_bank_path), 'qos_reliability': 'reliable'},
                       tmp_path / 'node.log', command=[str(exe)], base_env=env)
    harness = Harness('colcon_node_test')
    try:
        answers = harness.collect(PointCloud2, '/point_gn_classifier/classifications',
                                  reliable_qos())
        pub = harness.node.create_publisher(PointCloud2, 'segmented_objects', reliable_qos())
        harness.wait_for_subscribers([pub], node, 60.0)
        xyz, _, _ = load_modelnet_subset('test', 1)
        rng = np.random.default_rng(0)
        clouds = [to_sensor_frame(c, rng) for c in xyz[:4]]
        for i, cloud in enumerate(clouds):
            pub.publish(cloud_msg(cloud, 'lidar', stamp(100 + i)))
        assert harness.spin_until(lambda: len(answers) >= 4, 60.0), node.log()
        by_stamp = {stamp_key(m.header): m for m in answers}
        from point_gn_ros import decode_classifications
        labels = [int(decode_classifications(by_stamp[(100 + i, 0)])['class_id'][0])
                  for i in range(4)]
        assert_same_labels(labels, small_bank_path, clouds)
        # the process is the installed script, not this checkout's module
        assert Path(open(f'/proc/{node.pid}/cmdline', 'rb').read().split(b'\0')[1].decode()
                    ) == exe
        assert node.stop() == 0
    finally:
        harness.close()
        if node.proc.poll() is None:
            node.stop()


def _node_processes_with(marker: str) -> list[int]:
    """PIDs of processes whose command line mentions `marker` (a unique temp path)."""
    pids = []
    for proc in Path('/proc').iterdir():
        if proc.name.isdigit():
            try:
                if marker.encode() in (proc / 'cmdline').read_bytes():
                    pids.append(int(proc.name))
            except OSError:
                pass
    return pids


_SIGINT_DEFAULT_EXEC = ('import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); '
                        'os.execvp(sys.argv[1], sys.argv[1:])')


def test_ros2_launch_and_cli_control(colcon_install: Path, small_bank_path: Path,
                                     tmp_path: Path) -> None:
    """`ros2 launch` starts the installed node; `ros2 param set` and `ros2 lifecycle set` work.

    Answers arrive as vision_msgs/Detection3DArray on ~/detections.
    """
    import signal

    from conftest import load_modelnet_subset
    from node_testing import (DOMAIN_ID, Harness, reliable_qos, require_ros_extras, stamp,
                              stamp_key, to_sensor_frame, cloud_msg)
    require_ros_extras('launch_ros')
    require_ros_extras('ros2lifecycle')
    require_ros_extras('vision_msgs.msg')
    from sensor_msgs.msg import PointCloud2
    from vision_msgs.msg import Detection3DArray

    bank = tmp_path / 'launch_bank.npz'          # a unique path: finds the node's process
    shutil.copy(small_bank_path, bank)
    env = dict(_installed_env(colcon_install), ROS_DOMAIN_ID=str(DOMAIN_ID),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    log = open(tmp_path / 'launch.log', 'wb')  # noqa: SIM115 - closed below
    # As from a terminal: SIGINT at its default. A test run started as a background job of a
    # non-interactive shell inherits SIGINT *ignored*, exec keeps that, and ros2 launch then
    # never sees the Ctrl-C this test sends (the launch hung until killed).
    launch = subprocess.Popen(
        [sys.executable, '-c', _SIGINT_DEFAULT_EXEC, 'ros2', 'launch', 'point_gn_ros',
         'classifier.launch.py', 'namespace:=robot', f'bank_path:={bank}',
         'input_topics:=[launch_objects]', 'allow_parameter_changes:=true'],
        stdout=log, stderr=subprocess.STDOUT, env=env)
    node = '/robot/point_gn_classifier'
    harness = Harness('launch_test')

    def cli(*args: str) -> str:
        out = subprocess.run(['ros2', *args, '--no-daemon', '--spin-time', '5'], env=env,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stdout + out.stderr
        return out.stdout

    def text() -> str:
        return (tmp_path / 'launch.log').read_text(errors='replace')

    try:
        dets = harness.collect(Detection3DArray, f'{node}/detections', reliable_qos(50))
        pub = harness.node.create_publisher(PointCloud2, '/robot/launch_objects',
                                            reliable_qos(10))
        assert harness.spin_until(lambda: pub.get_subscription_count() > 0
                                  or launch.poll() is not None, 120.0), text()
        assert launch.poll() is None, text()
        harness.spin_for(0.5)
        xyz, _, _ = load_modelnet_subset('test', 1)
        rng = np.random.default_rng(0)
        clouds = [to_sensor_frame(c, rng) for c in xyz[:3]]

        def answered(i: int, timeout: float = 30.0) -> bool:
            pub.publish(cloud_msg(clouds[i], 'lidar', stamp(200 + i)))
            return harness.spin_until(
                lambda: any(stamp_key(d.header) == (200 + i, 0) for d in dets), timeout)

        def results(i: int) -> int:
            return next(len(d.detections[0].results) for d in dets
                        if stamp_key(d.header) == (200 + i, 0))

        assert answered(0), text()
        assert results(0) == 5
        assert 'successful' in cli('param', 'set', node, 'top_k', '3').lower()
        assert answered(1) and results(1) == 3
        assert 'active' in cli('lifecycle', 'get', node)
        cli('lifecycle', 'set', node, 'deactivate')
        assert 'inactive' in cli('lifecycle', 'get', node)
        assert not answered(2, 3.0)
        cli('lifecycle', 'set', node, 'activate')
        harness.spin_until(lambda: pub.get_subscription_count() > 0, 30.0)
        harness.spin_for(0.5)
        assert answered(2), text()
    finally:
        harness.close()
        launch.send_signal(signal.SIGINT)
        try:
            rc = launch.wait(30)
        except subprocess.TimeoutExpired:
            launch.kill()
            rc = launch.wait(5)
        log.close()
        leftovers = _node_processes_with(str(bank))
        for pid in leftovers:
            os.kill(pid, signal.SIGKILL)
    assert rc == 0, text()
    assert not leftovers, 'the node outlived ros2 launch'
    assert 'Traceback' not in text(), text()


def test_launch_arguments_reach_the_node_and_sigterm_stops_it(
        colcon_install: Path, small_bank_path: Path, tmp_path: Path) -> None:
    """Launch arguments segment_field, up_axis, unknown_threshold, qos_reliability work.

    Then `kill -TERM` on ros2 launch (which exits without stopping its processes) stops the
    node as well.
    """
    import signal
    import time

    from node_testing import DOMAIN_ID, require_ros_extras
    require_ros_extras('launch_ros')
    require_ros_extras('ros2param')

    name = f'launch_args_{os.getpid()}'           # unique: finds the node's process
    marker = f'__node:={name}'                    # (launch passes parameters in a file)
    env = dict(_installed_env(colcon_install), ROS_DOMAIN_ID=str(DOMAIN_ID),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    log_path = tmp_path / 'launch.log'
    log = open(log_path, 'wb')  # noqa: SIM115 - closed below
    launch = subprocess.Popen(
        ['ros2', 'launch', 'point_gn_ros', 'classifier.launch.py', f'node_name:={name}',
         f'bank_path:={small_bank_path}', 'input_topics:=[launch_args_objects]',
         'segment_field:=label',
         'up_axis:=-z', 'unknown_threshold:=0.25', 'qos_reliability:=best_effort'],
        stdout=log, stderr=subprocess.STDOUT, env=env)

    def text() -> str:
        return log_path.read_text(errors='replace')

    expected = ('classifying /launch_args_objects (best_effort, segment field label, up axis '
                '-z)')
    try:
        end = time.monotonic() + 120
        while expected not in text() and launch.poll() is None and time.monotonic() < end:
            time.sleep(0.2)
        assert expected in text(), text()
        out = subprocess.run(['ros2', 'param', 'get', f'/{name}', 'unknown_threshold',
                              '--no-daemon', '--spin-time', '5'], env=env, capture_output=True,
                             text=True, timeout=120)
        assert '0.25' in out.stdout, out.stdout + out.stderr
        assert _node_processes_with(marker)
        launch.send_signal(signal.SIGTERM)
        launch.wait(30)
        end = time.monotonic() + 30
        while _node_processes_with(marker) and time.monotonic() < end:
            time.sleep(0.2)
        leftovers = _node_processes_with(marker)
    finally:
        if launch.poll() is None:
            launch.kill()
            launch.wait(5)
        log.close()
        for pid in _node_processes_with(marker):
            os.kill(pid, signal.SIGKILL)
    assert not leftovers, 'the node outlived ros2 launch after SIGTERM:\n' + text()
