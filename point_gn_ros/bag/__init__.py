"""Rosbag tools: write dataset splits as PointCloud2 bags with ground truth, replay them.

Bag layout (written by ``writer.write_bag``, read by ``reader.read_bag``):

* the cloud topic (default ``/segmented_objects``, sensor_msgs/msg/PointCloud2): FLOAT32 x, y,
  z, INT32 ``gt_label`` (class index, the same for every point of an object) and, when a
  message holds several objects, INT32 ``segment`` (0..n-1). Header stamps are strictly
  increasing: they are the key that matches the classifier's answers to the messages;
* ``/point_gn/class_names`` (std_msgs/msg/String, offered transient-local): one class name
  per line (line index = ``gt_label``), written once before the first cloud;
* the bag metadata ``custom_data``: ``point_gn.class_names`` (the same text) and a few more
  ``point_gn.*`` keys describing how the bag was made.

Nothing here imports rclpy except ``replay``; writing and offline replay need no ROS graph.
"""

DEFAULT_TOPIC = '/segmented_objects'
CLASS_NAMES_TOPIC = '/point_gn/class_names'
GT_FIELD = 'gt_label'
SEGMENT_FIELD = 'segment'
POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
STRING = 'std_msgs/msg/String'
META_PREFIX = 'point_gn.'
# The node's default min_points: smaller objects are rejected, so offline replay skips them too.
DEFAULT_MIN_POINTS = 16
