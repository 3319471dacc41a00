"""The package builds with colcon and its installed executables run, as `ros2 run` would."""

import os
from pathlib import Path
import shutil
import subprocess
import sys

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


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
