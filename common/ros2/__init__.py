"""ROS 2 over Zenoh without a ROS install, as rmw_zenoh puts it on the wire: keys, liveliness
tokens and attachments (rmw), the ROS message types and CDR (msgs, with rosbags), and the thin
Zenoh shell that declares a ROS node, publishers and subscriptions (graph). The bridge service
(services/ros2) and capture's `--source ros2` both stand on it; our messages as ROS messages are
cores/ros2_convert.py."""
