"""Command-line tools: the bring-up supervisor (the suite as supervised processes) and the ros2 stand-in."""
