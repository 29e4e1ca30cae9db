"""comper_agent: the learners (COMPER, COMCACT, and their DQN / DDPG baselines) and the Q-target
network QT. The torch-only cores live in :mod:`comper_agent.core` (no ROS imports); the ROS nodes
wrap them."""
