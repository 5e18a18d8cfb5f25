"""ROS 2 without rclpy: the messages (:mod:`~egcbf.ros.messages`), pure codecs between them and one agent's
controller inputs and commands (:mod:`~egcbf.ros.codecs`), one agent's node logic (:mod:`~egcbf.ros.bridge`) and its
rclpy node (:mod:`~egcbf.ros.node`, needs ROS 2), and episode recordings as MCAP (:mod:`~egcbf.ros.record`).
Needs the ``ros`` extra (``rosbags``, ``mcap``) when used, not when imported; docs/ros.md."""
