"""``python -m cgags_ros.register_node`` / ``ros2 run cgags_ros register_node``."""

from .ros.node import main

if __name__ == '__main__':
    main()
