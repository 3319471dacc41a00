"""The classifier node's parameters: names, defaults, descriptions, ranges and validation.

No rclpy here: the node declares these (`descriptors()`), tests and tools read them.
`settings_from_values` turns the declared values into a validated, immutable `Settings`;
`unknown_override_warnings` catches misspelt overrides.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

from point_gn_ros.bank.classifier import unknown_rules
from point_gn_ros.bank.taught import DEFAULT_FIT_THRESHOLD
from point_gn_ros.core.surface import DEFAULT_SCENE_THRESHOLD, DEFAULT_VOLUME_THRESHOLD
from point_gn_ros.errors import PointGNError
from point_gn_ros.node.frames import UP_AXES
from point_gn_ros.recognizer import rule_thresholds as recognizer_rules


class NodeConfigError(PointGNError):
    """A parameter value the node cannot run with."""


@dataclass(frozen=True)
class TopicSettings:
    """What may differ between input topics (`topics.<key>.<name>` parameters)."""

    segment_field: str
    up_axis: str
    qos_reliability: str


@dataclass(frozen=True)
class NoSegment:
    """Segment ids that mark unsegmented points (`no_segment_ids`), never an object.

    negative: every id < 0; type_max: the largest value of an unsigned field's type (255,
    65535, 0xFFFFFFFF: PCL's and many pipelines' "no label"); ids: any other listed id.
    """

    negative: bool = True
    type_max: bool = True
    ids: frozenset[int] = frozenset()

    @classmethod
    def parse(cls, entries: Any) -> NoSegment:
        """From the parameter's strings: 'negative', 'max' or integers. NodeConfigError."""
        negative = type_max = False
        ids = set()
        for entry in entries:
            text = str(entry).strip().lower()
            if text == 'negative':
                negative = True
            elif text == 'max':
                type_max = True
            else:
                try:
                    ids.add(int(text, 0))
                except ValueError:
                    raise NodeConfigError(
                        f"parameter no_segment_ids: {entry!r} is not 'negative', 'max' or an "
                        'integer id') from None
        return cls(negative, type_max, frozenset(ids))


@dataclass(frozen=True)
class Settings:
    """Validated parameter values; the LIVE ones may be replaced while the node runs."""

    bank_path: str
    input_topics: tuple[str, ...]
    segment_field: str
    min_points: int
    max_points_per_message: int
    max_objects_per_message: int
    num_points: int
    resample: str
    device: str
    top_k: int
    unknown_threshold: float
    max_batch: int
    queue_size: int
    qos_reliability: str
    qos_depth: int
    torch_threads: int
    encoder_threads: int = 2
    up_axis: str = 'auto'
    input_timeout_s: float = 10.0
    marker_lifetime_s: float = 2.0
    autostart: bool = True
    search: str = 'auto'
    object_test: bool = True
    metric_size: bool = True
    fit_threshold: float = DEFAULT_FIT_THRESHOLD
    volume_threshold: float = DEFAULT_VOLUME_THRESHOLD
    scene_threshold: float = DEFAULT_SCENE_THRESHOLD
    allow_parameter_changes: bool = False
    no_segment_ids: tuple[str, ...] = ('negative', 'max')
    # One per input topic (same order): its own segment field, up axis and QoS.
    topics: tuple[TopicSettings, ...] = ()

    def topic(self, index: int) -> TopicSettings:
        """Input topic `index`'s settings: its `topics.<key>.*` overrides, else the node's."""
        if self.topics:
            return self.topics[index]
        return TopicSettings(self.segment_field, self.up_axis, self.qos_reliability)

    @property
    def unsegmented(self) -> NoSegment:
        return NoSegment.parse(self.no_segment_ids)


def _int_range(lo: int, hi: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=lo, to_value=hi, step=1)]


def _float_range(lo: float, hi: float) -> list[FloatingPointRange]:
    return [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]


# name -> (default, description, extra ParameterDescriptor kwargs). Those in LIVE can be set
# while the node runs; the others are read-only: they shape what configure builds (bank,
# encoder, subscriptions, QoS).
PARAMETERS: dict[str, tuple[Any, str, dict[str, Any]]] = {
    'bank_path': ('', "Feature bank (.npz); '' = the ModelNet40 bank shipped with the package.",
                  {}),
    'input_topics': (['segmented_objects'],
                     'sensor_msgs/PointCloud2 topics to classify (all share one worker).', {}),
    'segment_field': ('', "'' = each message is one object; else the integer point field that "
                          'splits a message into objects (ids in no_segment_ids are '
                          'unsegmented points). Per topic: topics.<key>.segment_field.', {}),
    'no_segment_ids': (['negative', 'max'],
                       "Segment ids that mean 'no segment' (points left out, never an object): "
                       "'negative' (every id < 0), 'max' (the largest value of an unsigned "
                       "field's type: 255, 65535, 0xFFFFFFFF) and/or integer ids as strings "
                       "('0' for a background label).", {}),
    'min_points': (16, 'Objects (or segments) with fewer finite points are rejected.',
                   {'integer_range': _int_range(1, 1_000_000)}),
    # The two limits bound one message's service time (docs/NODE.md, "Limits").
    'max_points_per_message': (500_000, 'Messages with more points are rejected unread '
                                        '(counted as rejected.too many points).',
                               {'integer_range': _int_range(1, 50_000_000)}),
    'max_objects_per_message': (64, 'Most objects classified per message: beyond it only the '
                                    'largest segments are kept (objects_truncated).',
                                {'integer_range': _int_range(1, 100_000)}),
    'num_points': (1024, "Points per object after resampling; must equal the bank's encoder "
                         'configuration.', {'integer_range': _int_range(16, 65536)}),
    'resample': ('fps', "Resampling to num_points: 'fps' (farthest point) or 'random'.",
                 {'additional_constraints': "one of 'fps', 'random'"}),
    'device': ('cpu', "Torch device: 'cpu' or 'cuda'.",
               {'additional_constraints': "one of 'cpu', 'cuda'"}),
    'top_k': (5, 'How many best classes (ids and scores) each object carries.',
              {'integer_range': _int_range(1, 100)}),
    'unknown_threshold': (0.0, 'Top-1 scores below it are labelled unknown (class_id -1); '
                               "0 = off, < 0 = the bank's calibrated threshold.",
                          {'floating_point_range': _float_range(-1.0, 1.0)}),
    'max_batch': (32, 'Most objects encoded in one micro-batch (across topics).',
                  {'integer_range': _int_range(1, 1024)}),
    'queue_size': (16, 'Messages waiting per input topic; when full the oldest is dropped. '
                       'Under overload the worker takes them as one batch: 16 answers ~13 % '
                       'more a second than 8 (the classifier reads its bank once a batch), '
                       'each about twice as late.',
                   {'integer_range': _int_range(1, 10_000)}),
    'qos_reliability': ('auto', "Input QoS reliability: 'auto' (match the publishers found on "
                                "each topic, re-checked as they come and go: best_effort if any "
                                "is best effort, else reliable), 'reliable' (no object lost in "
                                "transport) or 'best_effort' (objects > ~600 KB can be lost to "
                                'fragmentation; docs/NODE.md). Per topic: '
                                'topics.<key>.qos_reliability.',
                        {'additional_constraints': "one of 'auto', 'best_effort', 'reliable'"}),
    'qos_depth': (20, 'Input (and output) QoS history depth: what DDS holds for the node '
                      'while its intake thread is not scheduled; the counted dropping is '
                      "queue_size's.",
                  {'integer_range': _int_range(1, 1000)}),
    'torch_threads': (1, 'Torch intra-op threads (the classifier). 1: its per-batch products '
                         'are small, and a second torch thread spins instead of working '
                         '(node CPU per answer).',
                      {'integer_range': _int_range(1, 256)}),
    'encoder_threads': (2, 'Fast-encoder worker threads (batches; a lone cloud uses a second '
                           'one only while the machine is idle); bounded on purpose so that '
                           'they do not starve the executor and DDS threads.',
                        {'integer_range': _int_range(1, 256)}),
    'up_axis': ('auto', "Which axis of the input frame points up; objects are turned z-up "
                        "before classification. 'auto' = -y for frames named *_optical_frame "
                        "(REP 103), else z; or one of z, -z, y, -y, x, -x for every frame. "
                        'Per topic: topics.<key>.up_axis.',
                {'additional_constraints': "one of 'auto', 'z', '-z', 'y', '-y', 'x', '-x'"}),
    'input_timeout_s': (10.0, 'Diagnostics go WARN when an input topic has had no publisher or '
                              'no message for this long (s); 0 = never.',
                        {'floating_point_range': _float_range(0.0, 86400.0)}),
    'marker_lifetime_s': (2.0, 'Lifetime of the RViz markers (s), so that objects vanish when '
                               'answers stop; 0 = until replaced.',
                          {'floating_point_range': _float_range(0.0, 3600.0)}),
    'search': ('auto', "Bank search: 'exact' (every bank entry), 'indexed' (int8 coarse scan, "
                       "exact rescoring of the best 512; built at bank load) or 'auto' "
                       '(indexed from 20,000 entries on the CPU).',
               {'additional_constraints': "one of 'auto', 'exact', 'indexed'"}),
    'object_test': (True, "Apply the bank's object test to classes taught by enrollment "
                          '(bank/model.py: a taught class gains on scans nearer its object '
                          'than any built one, loses on the others); false = the head alone. '
                          'Banks without one (format < 6): no effect.', {}),
    'metric_size': (True, 'Input clouds are in metres (z up after up_axis): their measured size '
                          'is evidence against classes of implausible size, and taught classes '
                          'keep the sizes of their examples (bank/taught.py, docs/SIZE.md); '
                          'false for inputs without metric meaning (unit-sphere data).', {}),
    'fit_threshold': (
        DEFAULT_FIT_THRESHOLD,
        'Unknown (class_id -1) when the shape-and-size fit to the nearest class (with '
        'metric_size and taught classes with sizes: the nearest taught class) is below it, or '
        "(with metric_size) the size lies outside the answer's size region (bank/taught.py): "
        'garbage decodes, clouds of a size no class has, objects unlike every taught one; '
        '-10 = off (docs/SIZE.md for the trade-off).',
        {'floating_point_range': _float_range(-10.0, 1.0)}),
    'volume_threshold': (
        DEFAULT_VOLUME_THRESHOLD,
        "Unknown (class_id -1) when more than this share of the cloud's local neighbourhoods "
        'is volumetric (core/surface.py): a volume of random points, not a view of surfaces; '
        '1.0 = off (docs/SIZE.md for the trade-off).',
        {'floating_point_range': _float_range(0.0, 1.0)}),
    'scene_threshold': (
        DEFAULT_SCENE_THRESHOLD,
        'Unknown (class_id -1) when more than this share of the area the cloud covers seen '
        'from above lies apart from its largest part, a floor or table top under it left out, '
        'or when that support holds most points and is far wider than what stands on it '
        '(core/surface.py): several objects or a whole scene, not one segmented object; '
        '1.0 = off (docs/SIZE.md for the trade-off).',
        {'floating_point_range': _float_range(0.0, 1.0)}),
    'autostart': (True, 'Walk the lifecycle to active at start (configure + activate), as a '
                        'plain node; false = wait for a lifecycle manager.', {}),
    'allow_parameter_changes': (False, 'Let `ros2 param set` (any peer on the ROS domain: '
                                       'parameter services are unauthenticated without SROS2) '
                                       'change the live parameters while the node runs; '
                                       'false = every parameter is fixed at start.', {}),
}

QOS_CHOICES = ('auto', 'reliable', 'best_effort')
# Per-topic parameters: topics.<key>.<name>, <key> = the input_topics entry without its
# leading '/', each further '/' written '.' (topics.lidar.clusters.segment_field).
TOPIC_PREFIX = 'topics.'
TOPIC_PARAMETERS = ('segment_field', 'up_axis', 'qos_reliability')

# Parameters that take effect while the node runs (validated, applied between batches).
LIVE = frozenset({'top_k', 'unknown_threshold', 'queue_size', 'marker_lifetime_s',
                  'input_timeout_s'})

CHOICES = {'resample': ('fps', 'random'), 'device': ('cpu', 'cuda'),
           'qos_reliability': QOS_CHOICES, 'up_axis': UP_AXES,
           'search': ('auto', 'exact', 'indexed')}


def topic_key(topic: str) -> str:
    """The <key> of an input topic's `topics.<key>.<name>` parameters: '/a/b' -> 'a.b'."""
    return topic.strip('/').replace('/', '.')


def split_topic_parameter(name: str) -> tuple[str, str] | None:
    """'topics.a.b.segment_field' -> ('a.b', 'segment_field'); None if not topics.*."""
    if not name.startswith(TOPIC_PREFIX):
        return None
    key, _, setting = name[len(TOPIC_PREFIX):].rpartition('.')
    return key, setting


def topic_settings(values: dict[str, Any], topics: tuple[str, ...],
                   overrides: dict[str, Any]) -> tuple[TopicSettings, ...]:
    """Each input topic's settings: the node's, replaced by its `topics.<key>.*` overrides.

    Raises NodeConfigError for a key that names no input topic, an unknown setting name or
    a value outside the setting's choices.
    """
    keys = {topic_key(t): i for i, t in enumerate(topics)}
    per = [{name: values[name] for name in TOPIC_PARAMETERS} for _ in topics]
    for name, value in sorted(overrides.items()):
        key, setting = split_topic_parameter(name) or ('', '')
        if setting not in TOPIC_PARAMETERS:
            hint = closest_parameter(setting, TOPIC_PARAMETERS)
            raise NodeConfigError(f'parameter {name}: {setting!r} is not a per-topic setting '
                                  f'({", ".join(TOPIC_PARAMETERS)})'
                                  + (f"; did you mean '{hint}'?" if hint else ''))
        if key not in keys:
            raise NodeConfigError(f'parameter {name}: {key!r} is no input topic (keys: '
                                  f'{", ".join(keys)}; topics.<input topic without the '
                                  "leading '/', '/' written '.'>.<setting>)")
        choices = CHOICES.get(setting)
        if choices is not None and value not in choices:
            raise NodeConfigError(f'parameter {name}={value!r} must be one of '
                                  f'{", ".join(choices)}')
        per[keys[key]][setting] = str(value)
    return tuple(TopicSettings(**p) for p in per)


def settings_from_values(values: dict[str, Any],
                         topic_overrides: dict[str, Any] | None = None) -> Settings:
    """Validate declared parameter values (name -> value) into Settings.

    topic_overrides: the `topics.<key>.<name>` parameters (name -> value). Ranges are
    enforced by the descriptors when declared; this checks what they cannot express
    (choices, topic lists, CUDA availability). Raises NodeConfigError.
    """
    values = dict(values)
    for name, choices in CHOICES.items():
        if values[name] not in choices:
            raise NodeConfigError(f'parameter {name}={values[name]!r} must be one of '
                                  f'{", ".join(choices)}')
    topics = tuple(str(t) for t in values['input_topics'] or ())
    if not topics or any(not t for t in topics):
        raise NodeConfigError(f'parameter input_topics={list(topics)} must name at least '
                              'one topic, none empty')
    if len(set(topics)) != len(topics):
        raise NodeConfigError(f'parameter input_topics={list(topics)} repeats a topic')
    values['input_topics'] = topics
    values['no_segment_ids'] = tuple(str(v) for v in values.get('no_segment_ids') or ())
    NoSegment.parse(values['no_segment_ids'])          # raises on a bad entry
    values['topics'] = topic_settings(values, topics, topic_overrides or {})
    if values['device'] == 'cuda':
        import torch
        if not torch.cuda.is_available():
            raise NodeConfigError("parameter device='cuda' but CUDA is not available")
    return Settings(**values)


def rule_thresholds(s: Settings) -> dict[str, float | None]:
    """The Recognizer's fit, volume and scene rules (None: off) from the node's settings."""
    return recognizer_rules(s.fit_threshold, s.volume_threshold, s.scene_threshold)


def resolve_unknown_threshold(bank: Any, value: float) -> float | None:
    """The probability threshold the Classifier applies for `value`.

    As bank/classifier.py `unknown_rules` resolves it: None when off, or when the bank's
    calibration thresholds novelty.

    Raises NodeConfigError where the Classifier would refuse value (< 0, no calibration).
    """
    try:
        return unknown_rules(bank, value).probability
    except ValueError as exc:
        raise NodeConfigError(str(exc)) from None


def descriptors(allow_changes: bool = False) -> dict[str, tuple[Any, ParameterDescriptor]]:
    """Name -> (default, ParameterDescriptor) for declaring every parameter.

    allow_changes: the LIVE ones are writable (`allow_parameter_changes`); else all read-only.
    """
    out = {}
    for name, (default, description, extra) in PARAMETERS.items():
        desc = ParameterDescriptor(description=description,
                                   read_only=not (allow_changes and name in LIVE), **extra)
        if isinstance(default, list):   # an explicit type, so that [] would still be valid
            desc.type = ParameterType.PARAMETER_STRING_ARRAY
        out[name] = (default, desc)
    return out


# Overrides that are legitimate although not in PARAMETERS (rclpy's own, set by the node).
_FOREIGN = ('use_sim_time', 'start_type_description_service', 'class_names')


def unknown_override_warnings(names: Any) -> list[str]:
    """One warning per override name the node does not know, naming the closest valid one.

    A misspelt `-p name:=...` or YAML key is otherwise silently ignored by rclpy.
    """
    out = []
    for name in sorted(names):
        if (name in PARAMETERS or name in _FOREIGN or name.startswith('qos_overrides.')
                or name.startswith(TOPIC_PREFIX)):     # checked by topic_settings
            continue
        hint = closest_parameter(name, PARAMETERS)
        out.append(f"unknown parameter '{name}' ignored"
                   + (f"; did you mean '{hint}'?" if hint else
                      f" (parameters: {', '.join(PARAMETERS)})"))
    return out


def closest_parameter(name: str, known: Any) -> str | None:
    """The known parameter name closest to a misspelt one (difflib), or None."""
    import difflib
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return close[0] if close else None
