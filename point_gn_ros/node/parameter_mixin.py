"""ClassifierNode's ROS parameters: declaration, misspelt overrides, live changes, class_names.

A mixin of ClassifierNode (node/classifier_node.py): the table, defaults and validation are
node/params.py (no rclpy); this is the part that talks to the rclpy Node. `class_names` is
declared here as well: read-only, set from the bank whenever the node adopts a recognizer.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.parameter import Parameter

from point_gn_ros.node.params import (LIVE, PARAMETERS, TOPIC_PREFIX, NodeConfigError,
                                      closest_parameter, descriptors, resolve_unknown_threshold,
                                      unknown_override_warnings)

__all__ = ['ParameterMixin']


class ParameterMixin:
    """ClassifierNode's parameter methods (it provides settings, recognizer, _queue, ...)."""

    @property
    def autostart(self) -> bool:
        return bool(self.get_parameter('autostart').value)

    def _declare_parameters(self) -> None:
        # Whether the live parameters are writable is itself fixed at start (an override).
        allow = self._parameter_overrides.get('allow_parameter_changes')
        for name, (default, desc) in descriptors(bool(allow and allow.value)).items():
            self.declare_parameter(name, default, desc)
        # Per-topic settings (params.topic_settings) exist only where given: each override
        # named topics.<key>.<setting> is declared as given, checked at configure.
        for name, param in self._parameter_overrides.items():
            if name.startswith(TOPIC_PREFIX) and not self.has_parameter(name):
                self.declare_parameter(name, param.value, ParameterDescriptor(
                    description='Per-input-topic setting (docs/NODE.md, "Per-topic '
                                'settings").', read_only=True, dynamic_typing=True))

    def _topic_values(self) -> dict[str, Any]:
        """The declared topics.<key>.<setting> parameters: name -> value."""
        return {name: p.value for name, p in self._parameters.items()
                if name.startswith(TOPIC_PREFIX)}

    def _warn_unknown_overrides(self) -> None:
        """Misspelt overrides, warned once the extensions have declared their parameters."""
        undeclared = [n for n in self._parameter_overrides if not self.has_parameter(n)]
        for warning in unknown_override_warnings(undeclared):
            self.get_logger().warning(warning)

    def _values(self) -> dict[str, Any]:
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _check_undeclared_parameters(self, parameter_list: list[Parameter]) -> None:
        """The check of rclpy, naming the undeclared parameter and the closest declared one.

        rclpy raises it with an empty list (`Invalid access to undeclared parameter(s): []`),
        which is what `ros2 param set` showed for a misspelt name.
        """
        try:
            super()._check_undeclared_parameters(parameter_list)
        except ParameterNotDeclaredException:
            names = [p.name for p in parameter_list if not self.has_parameter(p.name)]
            hints = [closest_parameter(n, self._parameters) for n in names]
            raise ParameterNotDeclaredException(
                [f"'{n}'" + (f" (did you mean '{h}'?)" if h else '')
                 for n, h in zip(names, hints, strict=True)]) from None

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Validate and apply live parameter changes; refuse what cannot change now."""
        changes = {}
        for p in params:
            if p.name == 'class_names' and not self._setting_class_names:
                return SetParametersResult(successful=False,
                                           reason='class_names comes from the bank (read-only)')
            if p.name in LIVE:
                changes[p.name] = p.value
        if not changes or self.settings is None:
            return SetParametersResult(successful=True)   # read at configure
        try:
            settings = dataclasses.replace(self.settings, **changes)
            resolve_unknown_threshold(self.recognizer.bank, settings.unknown_threshold)
        except (NodeConfigError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.settings = settings
        self._queue.resize(settings.queue_size)
        self._pipeline.update(settings)
        self.get_logger().info('parameters changed: ' + ', '.join(
            f'{k}={v!r}' for k, v in changes.items()))
        if 'unknown_threshold' in changes:
            self._publish_labels()
        return SetParametersResult(successful=True)

    def _set_recognizer(self, recognizer: Any) -> None:
        """Adopt a recognizer: class names (parameter and latched topics) follow its bank."""
        self.recognizer = recognizer
        self.class_names = list(recognizer.class_names)
        self._setting_class_names = True
        try:
            if self.has_parameter('class_names'):
                self.set_parameters([Parameter('class_names', Parameter.Type.STRING_ARRAY,
                                               self.class_names)])
            else:
                # Taken from the bank: an override on the command line is ignored.
                self.declare_parameter(
                    'class_names', self.class_names,
                    ParameterDescriptor(type=ParameterType.PARAMETER_STRING_ARRAY,
                                        description='Class names of the bank (index = '
                                                    'class_id); set by the node.'),
                    ignore_override=True)
        finally:
            self._setting_class_names = False
