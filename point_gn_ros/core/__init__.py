"""The Point-GN encoder and what feeds it: configuration, sampling, naive oracle, fast kernels.

No ROS and no bank here: clouds in, features out.
"""
