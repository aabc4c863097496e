"""
The node's wiring: the only package that imports rclpy and message types.

The lifecycle node (:mod:`.node`) declares its parameters (:mod:`.parameters`) and QoS
(:mod:`.qos`), decodes each cloud and hands it to the ROS-free engine (:mod:`cgags_ros.engine`),
whose decisions it publishes (:mod:`.outputs`, which builds the messages; :mod:`.transforms`,
TF; :mod:`.diagnostics`).
"""
