"""Python side of comper_msgs: array types and the one place that converts messages to numpy."""
