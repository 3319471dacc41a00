"""Helpers for the classifier node tests.

Real data, a tiny bank, the node in its own process, and an in-test rclpy participant on a
private ROS domain.

Kept out of conftest.py (owned by the datasets tests) and imported by the tests that start a node.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any

from conftest import MODELNET, ArrayDataset, load_modelnet_split
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
NODE_FQN = '/point_gn_classifier'

# The caller's ROS_DOMAIN_ID when set (whoever shares the machine chose it); else one random
# private DDS domain per test session, so that concurrent sessions never see each other.
DOMAIN_ID = int(os.environ.get('POINT_GN_TEST_DOMAIN_ID') or os.environ.get('ROS_DOMAIN_ID')
                or random.randint(1, 100))
# Node and client logs go here rather than ~/.ros/log (inherited by every node process).
os.environ.setdefault('ROS_LOG_DIR', str(Path(tempfile.gettempdir()) / 'point_gn_test_roslog'))

# A small encoder configuration: the node tests check plumbing, not accuracy, and the
# naive encoder at 1024 points would make them minutes long.
TEST_NUM_POINTS = 256
TEST_K = 32
BANK_CLASSES = ('airplane', 'bottle', 'chair', 'guitar', 'lamp', 'table')


def require_ros_extras(module: str = 'vision_msgs.msg') -> None:
    """Skip (fail under POINT_GN_REQUIRE_SHARED=1) when a ROS package without a wheel is absent.

    vision_msgs, launch_ros and ros2cli come from a ROS install, or on dev/CI machines from
    ../shared/ros/install-extras.sh (`make ros-extras`; `make test` sources them).
    """
    import importlib
    try:
        importlib.import_module(module)
    except ImportError:
        reason = (f'{module} is not importable: install ROS (ros-jazzy-vision-msgs, '
                  'ros-jazzy-launch-ros, ros-jazzy-ros2cli) or run `make ros-extras` and source '
                  '.venv/ros_extras/setup.bash (make test does)')
        if os.environ.get('POINT_GN_REQUIRE_SHARED') == '1':
            pytest.fail(reason + ' (POINT_GN_REQUIRE_SHARED=1)')
        pytest.skip(reason)


def pick(split: str, classes: Sequence[str], per_class: int, offset: int = 0
         ) -> tuple[np.ndarray, np.ndarray]:
    """`per_class` clouds of each named class: xyz (M, 1024, 3), labels (M,) (global ids)."""
    xyz, labels, names = load_modelnet_split(split)
    idx = np.concatenate([np.flatnonzero(labels == names.index(c))[offset:offset + per_class]
                          for c in classes])
    return xyz[idx], labels[idx]


def build_tiny_bank(path: Path, extra_sigmas: tuple[float, ...] = ()) -> Path:
    """A bank of 3 train clouds for each of BANK_CLASSES, small encoder config (seconds)."""
    from point_gn_ros.bank.builder import build_bank
    from point_gn_ros.core.config import EncoderConfig

    xyz, labels = pick('train', BANK_CLASSES, 3)
    all_names = load_modelnet_split('train')[2]
    local = np.array([BANK_CLASSES.index(all_names[i]) for i in labels], dtype=np.int64)
    cfg = EncoderConfig(num_points=TEST_NUM_POINTS, k=TEST_K, extra_sigmas=extra_sigmas)
    dataset = ArrayDataset(xyz, local, list(BANK_CLASSES), str(MODELNET))
    bank = build_bank(dataset, cfg, folds=3, progress=False, gammas=(10.0, 100.0, 1000.0),
                      standardize_options=('none',))
    return bank.save(path, dtype='float32')


def to_sensor_frame(xyz: np.ndarray, rng: np.random.Generator, noise: float = 0.002
                    ) -> np.ndarray:
    """A unit-sphere dataset cloud as seen by a sensor: metres, rotated about z, translated."""
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    scale = rng.uniform(0.3, 0.8)
    offset = np.array([rng.uniform(2, 6), rng.uniform(-2, 2), rng.uniform(0.0, 1.0)], np.float32)
    out = (xyz * scale) @ rot.T + offset
    out += rng.normal(0.0, noise, out.shape).astype(np.float32)
    return out.astype(np.float32)


def stamp(sec: int, nanosec: int = 0) -> Any:
    from builtin_interfaces.msg import Time
    return Time(sec=sec, nanosec=nanosec)


def now_stamp() -> Any:
    ns = time.time_ns()
    return stamp(ns // 1_000_000_000, ns % 1_000_000_000)


def cloud_msg(xyz: np.ndarray, frame_id: str, stamp_msg: Any,
              extra: dict[str, np.ndarray] | None = None) -> Any:
    """sensor_msgs/PointCloud2 with FLOAT32 x, y, z (+ extra fields)."""
    from std_msgs.msg import Header

    from point_gn_ros.pointcloud2 import xyz_to_pointcloud2
    return xyz_to_pointcloud2(Header(frame_id=frame_id, stamp=stamp_msg), xyz, extra)


def stamp_key(header: Any) -> tuple[int, int]:
    return (header.stamp.sec, header.stamp.nanosec)


# ------------------------------------------------------------------------------ node process


class NodeProcess:
    """`python -m point_gn_ros.node.classifier_node` in its own process, output in a log file."""

    def __init__(self, params: dict[str, Any], log_path: Path, domain_id: int = DOMAIN_ID,
                 extra_env: dict[str, str] | None = None,
                 params_file: Path | None = None, command: Sequence[str] | None = None,
                 base_env: dict[str, str] | None = None, node_name: str | None = None) -> None:
        """Start the node; command: the executable (default: this Python's `-m` module).

        node_name: a remapped name (`-r __node:=...`), so that no earlier test's node, still
        known to DDS discovery for a while after it exited, can answer for it.
        """
        args = list(command or [sys.executable, '-m', 'point_gn_ros.node.classifier_node'])
        args.append('--ros-args')
        if node_name:
            args += ['-r', f'__node:={node_name}']
        if params_file is not None:
            args += ['--params-file', str(params_file)]
        for key, value in params.items():
            args += ['-p', f'{key}:={_param_text(value)}']
        env = dict(base_env or os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1',
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', **(extra_env or {}))
        self.log_path = log_path
        self._log = open(log_path, 'wb')  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                     cwd=REPO)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def log(self) -> str:
        return self.log_path.read_text(errors='replace')

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            self._log.close()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Send `sig`, wait; SIGKILL if it does not exit. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


def _param_text(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_param_text(v) for v in value) + ']'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f"'{value}'" if value == '' or value.strip() != value else value
    return str(value)


@contextlib.contextmanager
def running_node(params: dict[str, Any], log_path: Path) -> Iterator[NodeProcess]:
    node = NodeProcess(params, log_path)
    try:
        yield node
    finally:
        node.stop()


# ------------------------------------------------------------------------------ test participant


class Harness:
    """An rclpy context/node on DOMAIN_ID with helpers to publish and collect."""

    def __init__(self, name: str = 'node_test') -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.received: dict[str, list[Any]] = {}
        self._clients: dict[tuple[Any, str], Any] = {}

    def collect(self, msg_type: Any, topic: str, qos: Any = 10) -> list[Any]:
        """Subscribe and append every message to a list (returned, also in .received)."""
        out = self.received.setdefault(topic, [])
        self.node.create_subscription(msg_type, topic, out.append, qos)
        return out

    def spin_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return predicate()

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def wait_for_subscribers(self, publishers: Sequence[Any], node: NodeProcess | None,
                             timeout: float = 60.0) -> None:
        """Until the node subscribes to every publisher's topic (or died / timed out)."""
        def ready() -> bool:
            if node is not None and node.proc.poll() is not None:
                raise AssertionError(f'node exited with {node.proc.returncode}:\n{node.log()}')
            return all(p.get_subscription_count() > 0 for p in publishers)
        if not self.spin_until(ready, timeout):
            raise AssertionError(f'node did not subscribe within {timeout} s:\n'
                                 + (node.log() if node else ''))

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 30.0,
             resend_s: float | None = None) -> Any:
        """Call service `name` and return its response (AssertionError on timeout).

        A server can drop a response when its reply writer has not yet matched this
        client's reply reader (a discovery race of ROS 2 services: `wait_for_service` only
        sees the request side; Fast DDS waits 100 ms, then drops it, ros2/ros2#1253). So the
        client of each service is made once and kept, and an idempotent request (a query)
        is sent again every `resend_s` seconds until one is answered.
        """
        client = self._clients.get((srv_type, name))
        if client is None:
            client = self._clients[srv_type, name] = self.node.create_client(srv_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f'no service {name}'
        end = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            wait = end - time.monotonic() if resend_s is None else \
                min(resend_s, end - time.monotonic())
            if self.spin_until(future.done, max(wait, 0.0)):
                return future.result()
            client.remove_pending_request(future)
            assert time.monotonic() < end, f'{name}: no response in {timeout} s'

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def latest_diagnostics(diags: list[Any], name_suffix: str = ': pipeline') -> dict[str, str]:
    """Map key -> value of the newest status whose name ends with name_suffix ({} if none)."""
    for arr in reversed(diags):
        for st in arr.status:
            if st.name.endswith(name_suffix):
                level = ord(st.level) if isinstance(st.level, bytes) else int(st.level)
                return {kv.key: kv.value for kv in st.values} | {'_message': st.message,
                                                                 '_level': str(level)}
    return {}


def offline_labels(bank_path: Path, clouds: Sequence[np.ndarray]) -> np.ndarray:
    """What the offline Recognizer says about the same clouds (the node must agree)."""
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.from_bank(bank_path)
    return rec.classify_clouds(list(clouds)).labels


def assert_same_labels(node_labels: Sequence[int], bank_path: Path,
                       clouds: Sequence[np.ndarray], tie: float = 1e-4) -> None:
    """The node's labels equal the offline Recognizer's for the same clouds.

    The offline side has the node's default unknown rules (`Recognizer.as_node`), as the
    nodes of these tests run at their defaults. Only a near-tie (top-2 scores within `tie`,
    where float rounding in a different batch may decide) may go to the runner-up.
    """
    from point_gn_ros.recognizer import Recognizer

    res = Recognizer.as_node(bank_path).classify_clouds(list(clouds))
    for i, got in enumerate(node_labels):
        if got == res.labels[i]:
            continue
        s = res.topk_scores[i]
        assert len(s) > 1 and s[0] - s[1] < tie and got == res.topk_ids[i, 1], (
            f'cloud {i}: node says {got}, offline {res.labels[i]} (top-k {res.topk_ids[i]} '
            f'{res.topk_scores[i]})')


def sensor_qos() -> Any:
    from rclpy.qos import qos_profile_sensor_data
    return qos_profile_sensor_data


def reliable_qos(depth: int = 10) -> Any:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def latched_qos() -> Any:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope='session')
def tiny_bank(tmp_path_factory: pytest.TempPathFactory, modelnet_dir: Path) -> Path:
    """The tiny node-test bank, built once per session (a few seconds).

    modelnet_dir (test/conftest.py) skips, or fails under POINT_GN_REQUIRE_SHARED=1, when
    the shared data is absent.
    """
    assert modelnet_dir == MODELNET
    path = tmp_path_factory.getbasetemp() / 'node_tiny_bank.npz'
    return path if path.is_file() else build_tiny_bank(path)


@pytest.fixture(scope='module')
def harness() -> Iterator[Harness]:
    h = Harness()
    try:
        yield h
    finally:
        h.close()
