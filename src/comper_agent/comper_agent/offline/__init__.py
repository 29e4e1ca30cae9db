"""Offline evaluation of recorded runs (bags, checkpoints): no ROS graph needed."""
