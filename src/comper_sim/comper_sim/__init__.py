"""comper_sim: the simulation bridge (gymnasium MuJoCo / classic control and ALE behind ROS 2 services).

The pure core is in :mod:`comper_sim.core` (no rclpy); :mod:`comper_sim.sim_node` is the thin node.
"""
