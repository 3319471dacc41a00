"""The ROS 2 node: a thin adapter over the ROS-free core (queue, stats, markers, logging)."""
