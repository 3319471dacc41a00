"""Vectorised sensor_msgs/PointCloud2 codec (no rclpy, no sensor_msgs_py).

- ``decode``: zero-copy decoding of any PointCloud2-like object (``decode_xyz``,
  ``split_segments``); every malformation raises ``DecodeError``.
- ``build``: packed little-endian ``sensor_msgs.msg.PointCloud2`` messages
  (``make_pointcloud2``, ``xyz_to_pointcloud2``).
- ``classifications``: the node's ``~/classifications`` output contract.
"""

from point_gn_ros.pointcloud2.build import make_pointcloud2, xyz_to_pointcloud2
from point_gn_ros.pointcloud2.classifications import (classification_fields,
                                                      decode_classifications,
                                                      make_classifications)
from point_gn_ros.pointcloud2.decode import (DEFAULT_MAX_POINTS, FLOAT32, FLOAT64, INT8, INT16,
                                             INT32, INT32_LIMIT, POINTFIELD_DTYPES, UINT8,
                                             UINT16, UINT32, DecodedCloud, decode_xyz,
                                             split_segments)

__all__ = ['DEFAULT_MAX_POINTS', 'FLOAT32', 'FLOAT64', 'INT8', 'INT16', 'INT32', 'INT32_LIMIT',
           'POINTFIELD_DTYPES', 'UINT8', 'UINT16', 'UINT32', 'DecodedCloud',
           'classification_fields', 'decode_classifications', 'decode_xyz',
           'make_classifications', 'make_pointcloud2', 'split_segments', 'xyz_to_pointcloud2']
