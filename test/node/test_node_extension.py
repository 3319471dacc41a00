"""The node's extension points, in process: managed extensions, diagnostic sources, bank swap."""

from __future__ import annotations

import gc
from pathlib import Path

import pytest

from node_testing import DOMAIN_ID, TEST_NUM_POINTS, tiny_bank

__all__ = ['tiny_bank']  # fixture, imported so that pytest finds it


def test_extensions_follow_the_lifecycle_and_banks_swap(tiny_bank: Path) -> None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticStatus
    from rclpy.lifecycle import ManagedEntity, TransitionCallbackReturn
    from rclpy.parameter import Parameter

    from point_gn_ros.node.classifier_node import ClassifierNode
    from point_gn_ros.node.params import NodeConfigError
    from point_gn_ros.recognizer import Recognizer

    calls: list[str] = []

    class Recorder(ManagedEntity):
        def __init__(self, node: ClassifierNode) -> None:
            self.node = node
            node.add_diagnostic_source(
                lambda name: DiagnosticStatus(name=f'{name}: recorder', message='ok'))

        def on_configure(self, state: object) -> TransitionCallbackReturn:
            calls.append(f'configure {len(self.node.class_names)}')   # after the bank loaded
            return TransitionCallbackReturn.SUCCESS

        def on_activate(self, state: object) -> TransitionCallbackReturn:
            calls.append('activate')
            return TransitionCallbackReturn.SUCCESS

        def on_cleanup(self, state: object) -> TransitionCallbackReturn:
            calls.append(f'cleanup {self.node.recognizer is not None}')  # before it is freed
            return TransitionCallbackReturn.SUCCESS

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    node = None
    try:
        node = ClassifierNode(context=context, extensions=[Recorder], parameter_overrides=[
            Parameter('bank_path', value=str(tiny_bank)),
            Parameter('num_points', value=TEST_NUM_POINTS)])
        assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert gc.get_freeze_count() > 0     # node/gc_pauses.py: start-up objects frozen
        assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
        assert calls == ['configure 6', 'activate']
        published: list = []
        node._pub_diag.publish = published.append                   # capture one report
        node._publish_diagnostics()
        assert published[0].status[-1].name == '/point_gn_classifier: recorder'
        assert node.get_parameter('class_names').value[0] == 'airplane'

        swapped = Recognizer.from_bank(tiny_bank)
        swapped.bank.class_names = [f'x{i}' for i in range(6)]     # a "re-built" bank
        node.replace_recognizer(swapped)
        assert node.class_names[0] == 'x0'
        assert node.get_parameter('class_names').value[0] == 'x0'
        assert node.set_parameters([Parameter('class_names', value=['a'])])[0].successful \
            is False                                               # only the node sets it
        with pytest.raises(NodeConfigError, match='num_points'):
            bad = Recognizer.from_bank(None)                       # 1024-point default bank
            node.replace_recognizer(bad)

        assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
        assert calls[-1] == 'cleanup True' and node.recognizer is None
        assert gc.get_freeze_count() == 0    # given back with the bank
    finally:
        if node is not None:
            node.destroy_node()
        context.try_shutdown()
