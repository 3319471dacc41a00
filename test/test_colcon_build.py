"""The package builds with colcon and its installed executables run, as `ros2 run` would."""

import os
from pathlib import Path
import shutil
import subprocess
import sys

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
