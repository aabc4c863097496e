"""
The node's wiring: the only package that imports rclpy and message types.

The lifecycle node (:mod:`.node`) converts messages (:mod:`.conversions`), declares its
parameters (:mod:`.parameters`) and QoS (:mod:`.qos`), and hands every cloud to the ROS-free
engine (:mod:`cgags_ros.engine`), whose decisions it publishes (:mod:`.outputs`,
:mod:`.diagnostics`).
"""
