"""comper_memory: the compact transition memory of COMPER / COMCACT (TM, RTM, similarity index).

The pure-Python core lives in :mod:`comper_memory.core` (no ROS imports); the ROS node wraps it.
"""
