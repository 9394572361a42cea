"""Converters from what labs record (raw folders, ROS bags) to the VisionForce MCAP layout."""
