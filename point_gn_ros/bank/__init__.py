"""The feature bank: file, transform, building, CV choice of knobs, classification. No ROS."""
