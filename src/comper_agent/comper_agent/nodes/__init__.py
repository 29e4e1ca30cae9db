"""The ROS 2 nodes of the agent package and what they share: the learner nodes (comcact_node, comper_node),
the actors and the QT trainer, their parameters, bring-up, links to the memory and the run's outputs.
The algorithms are in :mod:`comper_agent.core` (no ROS)."""
