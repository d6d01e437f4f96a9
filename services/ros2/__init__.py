"""The ROS 2 bridge service: obstacle lists, free space, the rectified image and /tf_static as ROS 2
topics on rmw_zenoh (common/ros2 for the wire, cores/ros2_convert.py for the messages)."""
