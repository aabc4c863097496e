"""
What register_node decides, without ROS: the engine the node wires to its topics.

:class:`~.engine.RegistrationEngine` pairs the node's clouds, runs the registration
process, keeps the accounting, answers relocalization requests and guards the initial
pose; the node (:mod:`cgags_ros.ros`) converts messages and publishes what the engine
hands it through :class:`~.interface.EngineOutputs`. Nothing here imports rclpy or a
message package, so every decision is tested without DDS (``test/test_engine.py``).
"""
