"""ROS 2 over Zenoh without a ROS install: what rmw_zenoh puts on the wire (rmw.py), the ROS message
types and CDR (msgs.py, with rosbags), our messages as ROS messages (convert.py), the thin Zenoh
shell that declares a ROS node, publishers and subscriptions (graph.py) and the bridge service
(main.py). capture's `--source ros2` (services/capture/ros2.py) uses the same pieces the other way.
"""
