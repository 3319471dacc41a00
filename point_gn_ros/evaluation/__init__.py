"""Accuracy metrics and few-shot episodes over datasets. No ROS."""
