"""One exception per way a bag can be unusable; each message names the bag and the problem."""

from point_gn_ros.errors import PointGNError


class BagError(PointGNError):
    """A bag cannot be written, read or replayed."""


class BagNotFoundError(BagError):
    """The path does not exist or is not a rosbag2 bag."""


class BagCorruptError(BagError):
    """The bag is truncated or its storage cannot be read."""


class EmptyBagError(BagError):
    """The bag (or its cloud topic) holds no messages."""


class MissingTopicError(BagError):
    """The requested (or any PointCloud2) topic is not in the bag."""


class WrongTypeError(BagError):
    """The cloud topic does not carry sensor_msgs/msg/PointCloud2."""


class NoGroundTruthError(BagError):
    """The bag has no class names or no per-point gt_label field."""


class ReplayError(BagError):
    """The live replay cannot run: no classifier node found, or the ROS graph failed."""
