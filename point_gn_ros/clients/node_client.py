"""Drive the classifier node from outside: start it as a process, feed it clouds, time answers.

Shared by the demo (`python -m point_gn_ros.clients.demo`) and the node benchmark
(`node_bench.bench_node`). The node runs in its own process, exactly as deployed; this
side is an ordinary rclpy participant on the same ROS domain.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

from point_gn_ros.core.sampling import rotate_z

DEMO_OBJECTS = Path(__file__).resolve().parents[1] / 'data' / 'demo_objects.npz'
NODE_FQN = '/point_gn_classifier'


@dataclass
class DemoObjects:
    """Held-out ModelNet40 test objects shipped with the package."""

    xyz: np.ndarray            # (M, N, 3) float32, unit sphere (dataset frame)
    labels: np.ndarray         # (M,) int64
    class_names: list[str]     # index = label
    source: list[str]          # dataset file of each object


def load_demo_objects(path: str | os.PathLike[str] = DEMO_OBJECTS) -> DemoObjects:
    """Read demo_objects.npz (plain arrays only, never unpickled)."""
    with np.load(path, allow_pickle=False) as z:
        return DemoObjects(xyz=z['xyz'].astype(np.float32), labels=z['labels'].astype(np.int64),
                           class_names=[str(n) for n in z['class_names']],
                           source=[str(s) for s in z['source']] if 'source' in z.files else [])


def place_in_sensor_frame(xyz: np.ndarray, rng: np.random.Generator, noise: float = 0.003,
                          yaw: float = 0.0, single_view: bool = False,
                          class_name: str | None = None) -> np.ndarray:
    """A unit-sphere object as a sensor sees it: metres, `yaw` radians about z, translated.

    single_view: only a simulated scan of the side facing the sensor at the origin (hidden
    points removed, sensor noise, dropout; core/views.py), as a depth camera or lidar sees it.
    The node normalises position and scale itself; a yaw-aligned bank (the shipped one)
    also undoes the yaw, any other bank needs the dataset's orientation (yaw 0).
    class_name: scale the object to a typical real size of its class (bank/taught.py
    `plausible_scale`, x 0.8-1.25), as the node's metric size expects; None: 0.4-1.0 x.
    """
    from point_gn_ros.bank.taught import plausible_scale
    scale = rng.uniform(0.4, 1.0) if class_name is None else \
        plausible_scale(xyz, class_name) * rng.uniform(0.8, 1.25)
    offset = np.array([rng.uniform(2.0, 8.0), rng.uniform(-3.0, 3.0), rng.uniform(0.0, 1.0)],
                      dtype=np.float32)
    if single_view:
        from point_gn_ros.core.views import simulate_view
        azimuth = float(np.arctan2(-offset[1], -offset[0]) - yaw)   # object frame -> sensor
        xyz = simulate_view(xyz, rng, azimuth=azimuth).points
    out = rotate_z(xyz * scale, yaw) + offset
    out += rng.normal(0.0, noise, out.shape)
    return out.astype(np.float32)


class NodeLauncher:
    """The classifier node in a child process (`python -m point_gn_ros.node.classifier_node`)."""

    def __init__(self, params: dict[str, Any], domain_id: int, log_path: Path | None = None,
                 passthrough: bool = False) -> None:
        args = [sys.executable, '-m', 'point_gn_ros.node.classifier_node', '--ros-args']
        for key, value in params.items():
            args += ['-p', f'{key}:={_param_text(value)}']
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        self._own_log = log_path is None and not passthrough
        if log_path is None:
            fd, name = tempfile.mkstemp(prefix='point_gn_node_', suffix='.log')
            os.close(fd)
            log_path = Path(name)
        self.log_path = log_path
        self._log = None if passthrough else open(log_path, 'wb')  # noqa: SIM115 - see stop()
        self.proc = subprocess.Popen(args, env=env, stdout=self._log,
                                     stderr=subprocess.STDOUT if self._log else None)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_tail(self, lines: int = 20) -> str:
        try:
            return '\n'.join(self.log_path.read_text(errors='replace').splitlines()[-lines:])
        except OSError:
            return ''

    def peak_rss_mb(self) -> float:
        """The node's peak resident memory (VmHWM), or NaN once it has exited."""
        try:
            for line in Path(f'/proc/{self.pid}/status').read_text().splitlines():
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) / 1024.0
        except OSError:
            pass
        return float('nan')

    def cpu_s(self) -> float:
        """CPU seconds (user + system) the node process has used, or NaN once it has exited.

        Robust on a shared machine, unlike wall-clock throughput.
        """
        try:
            fields = Path(f'/proc/{self.pid}/stat').read_text().rsplit(')', 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
        except (OSError, IndexError, ValueError):
            return float('nan')

    def stop(self, timeout: float = 20.0) -> int:
        """SIGINT, wait (SIGKILL after `timeout`); returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if self._log is not None:
            self._log.close()
        if self._own_log and self.proc.returncode == 0:
            self.log_path.unlink(missing_ok=True)   # kept when something went wrong
        return self.proc.returncode

    def __enter__(self) -> 'NodeLauncher':
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _param_text(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_param_text(v) for v in value) + ']'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str) and (value == '' or value != value.strip()):
        return f"'{value}'"
    return str(value)


@dataclass
class Answer:
    """One `~/classifications` message as received, with its local arrival time."""

    msg: Any
    received: float            # time.monotonic()


class Client:
    """An rclpy participant that publishes clouds and collects the node's answers by stamp.

    Answers are taken by a thread of their own (node/intake.py's `Intake`, as the node takes
    its input), not by the executor: rclpy's executor costs ~0.1-0.2 ms of Python a spin,
    and spinning it between 1,000 sends a second would take ~0.3 of a CPU from the node
    being measured. `answers` fills while
    the caller sleeps or spins; the executor serves the other subscriptions.
    """

    def __init__(self, domain_id: int, topic: str, reliable: bool = True,
                 name: str = 'point_gn_client') -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import (DurabilityPolicy, QoSProfile, ReliabilityPolicy,
                               qos_profile_sensor_data)
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = (QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE) if reliable
               else qos_profile_sensor_data)
        self.publisher = self.node.create_publisher(PointCloud2, topic, qos)
        self.answers: dict[tuple[int, int], Answer] = {}
        self.class_names: list[str] | None = None
        # The node's own counters (its /diagnostics pipeline status) and the report's stamp
        # (the node's clock: this machine's system time, s).
        self.counters: dict[str, str] = {}
        self.counters_stamp = 0.0
        from point_gn_ros.node.intake import Intake, NotForExecutors
        answers = self.node.create_subscription(
            PointCloud2, f'{NODE_FQN}/classifications', self._on_answer,
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE),
            callback_group=NotForExecutors())
        self._intake = Intake(self.context, [answers], lambda _, msg: self._on_answer(msg),
                              self._on_intake_error)
        self.node.create_subscription(
            String, f'{NODE_FQN}/class_names', self._on_names,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        from diagnostic_msgs.msg import DiagnosticArray
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 10)
        self._seq = 0

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if status.name == f'{NODE_FQN}: pipeline':
                self.counters = {kv.key: kv.value for kv in status.values}
                self.counters_stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec

    def fresh_counters(self, timeout: float = 3.0) -> dict[str, str]:
        """The node's counters from a report sent after this call ({} if none came).

        By the report's stamp, not its arrival: reports queued while the executor was not
        spun arrive first, and they are older than the call.
        """
        since = time.time()
        self.spin_until(lambda: self.counters_stamp > since, timeout)
        return self.counters if self.counters_stamp > since else {}

    def _on_answer(self, msg: Any) -> None:
        self.answers[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = Answer(
            msg, time.monotonic())

    @staticmethod
    def _on_intake_error(exc: Exception) -> None:
        print(f'point_gn client: taking an answer failed: {type(exc).__name__}: {exc}',
              file=sys.stderr, flush=True)

    def _on_names(self, msg: Any) -> None:
        self.class_names = msg.data.split('\n')

    def spin_until(self, predicate: Any, timeout: float, node: NodeLauncher | None = None
                   ) -> bool:
        end = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > end or (node is not None and not node.alive()):
                return bool(predicate())
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def wait_ready(self, node: NodeLauncher, timeout: float) -> bool:
        """Until the node subscribes to our topic and its class names have arrived."""
        return self.spin_until(lambda: self.publisher.get_subscription_count() > 0
                               and self.class_names is not None, timeout, node)

    def send(self, xyz: np.ndarray, frame_id: str,
             extra: dict[str, np.ndarray] | None = None) -> tuple[tuple[int, int], float]:
        """Publish one cloud stamped now (unique stamp); returns (stamp key, send time)."""
        from builtin_interfaces.msg import Time
        from std_msgs.msg import Header

        from point_gn_ros.pointcloud2 import xyz_to_pointcloud2
        ns = time.time_ns() + self._seq   # + seq: unique even within one clock tick
        self._seq += 1
        key = (ns // 1_000_000_000, ns % 1_000_000_000)
        header = Header(frame_id=frame_id, stamp=Time(sec=key[0], nanosec=key[1]))
        msg = xyz_to_pointcloud2(header, xyz, extra)
        sent = time.monotonic()
        self.publisher.publish(msg)
        return key, sent

    def close(self) -> None:
        self._intake.stop()                 # first: it waits on the answer subscription
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def percentiles_ms(latencies_s: Sequence[float]) -> tuple[float, float]:
    """(p50, p99) in milliseconds; NaN when empty."""
    if not latencies_s:
        return float('nan'), float('nan')
    p50, p99 = np.percentile(np.asarray(latencies_s) * 1e3, [50, 99])
    return float(p50), float(p99)
