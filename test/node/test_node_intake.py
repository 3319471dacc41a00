"""The input intake (node/intake.py): clouds are taken off DDS without the node's executor."""

from __future__ import annotations

from pathlib import Path
import threading
import time

import numpy as np

from node_testing import (BANK_CLASSES, DOMAIN_ID, TEST_NUM_POINTS, cloud_msg, pick, stamp,
                          stamp_key, tiny_bank, to_sensor_frame)

__all__ = ['tiny_bank']  # fixture, imported so that pytest finds it


def _intake_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == 'point_gn_intake']


def _os_thread_names() -> set[str]:
    return {(task / 'comm').read_text().strip() for task in Path('/proc/self/task').iterdir()}


def test_clouds_are_answered_while_the_executor_is_blocked(tiny_bank: Path) -> None:
    """Clouds are answered by a node whose executor never spins.

    As while a long service call runs: every cloud is still taken, classified and
    answered, and the intake follows the lifecycle.
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.lifecycle import TransitionCallbackReturn
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.node.classifier_node import ClassifierNode

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = client = None
    try:
        node = ClassifierNode(context=context, parameter_overrides=[
            Parameter('bank_path', value=str(tiny_bank)),
            Parameter('num_points', value=TEST_NUM_POINTS),
            Parameter('input_topics', value=['intake_objects']),
            Parameter('queue_size', value=100)])
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert not _intake_threads()                 # nothing taken before activate
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert len(_intake_threads()) == 1
        # named for the OS too, so that `top -H` tells the node's threads apart (each thread
        # names itself when it first runs: a loaded machine may take a moment to run it)
        deadline = time.monotonic() + 10.0
        while not {'point_gn_intake', 'point_gn_worker'} <= _os_thread_names() \
                and time.monotonic() < deadline:
            time.sleep(0.02)
        assert {'point_gn_intake', 'point_gn_worker'} <= _os_thread_names()

        # Another participant, spun by its own executor; the classifier node by none.
        client = rclpy.create_node('intake_test', context=context)
        answers: list = []
        client.create_subscription(PointCloud2, '/point_gn_classifier/classifications',
                                   answers.append, 100)
        pub = client.create_publisher(PointCloud2, 'intake_objects', 100)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(client)

        def spin_until(done, timeout: float) -> bool:
            end = time.monotonic() + timeout
            while time.monotonic() < end and not done():
                executor.spin_once(timeout_sec=0.05)
            return done()

        assert spin_until(lambda: pub.get_subscription_count() > 0 and
                          client.count_publishers('/point_gn_classifier/classifications'), 30)
        rng = np.random.default_rng(3)
        xyz, _ = pick('test', BANK_CLASSES, 1)
        keys = [(7000 + i, 0) for i in range(len(xyz))]
        for key, cloud in zip(keys, xyz, strict=True):
            pub.publish(cloud_msg(to_sensor_frame(cloud, rng), 'lidar', stamp(*key)))
        assert spin_until(lambda: len(answers) >= len(keys), 60), len(answers)
        assert sorted(stamp_key(m.header) for m in answers) == keys
        snap = node._stats.snapshot(node._queue.depths())
        assert snap.received == [len(keys)] and snap.processed == [len(keys)]

        # Deactivate stops the intake before its subscription goes; activate starts a new one.
        assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        assert not _intake_threads()
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert spin_until(lambda: pub.get_subscription_count() > 0, 30)
        pub.publish(cloud_msg(to_sensor_frame(xyz[0], rng), 'lidar', stamp(7100)))
        assert spin_until(lambda: any(stamp_key(m.header) == (7100, 0) for m in answers), 60)
        assert len(_intake_threads()) == 1
    finally:
        if node is not None:
            node.destroy_node()
        if client is not None:
            client.destroy_node()
        context.try_shutdown()
    assert not _intake_threads()                     # shut down with the node
