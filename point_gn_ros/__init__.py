"""point_gn_ros: training-free Point-GN object classification for ROS 2."""

__version__ = '0.1.0'


def decode_classifications(msg):  # noqa: ANN001, ANN201 - thin lazy re-export
    """Decode a `~/classifications` PointCloud2 into plain numpy arrays.

    See point_gn_ros.pointcloud2.decode_classifications.
    """
    from point_gn_ros.pointcloud2 import decode_classifications as _decode
    return _decode(msg)
