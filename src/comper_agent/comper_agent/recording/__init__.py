"""Recording: the recorder node, crash-safe rosbag2 writing, the learners' recording link and the bag tools."""
