"""``python -m cgags_ros.register_node`` / ``ros2 run cgags_ros register_node``."""

from .parallel import quiet_idle_threads


def main(args: list[str] | None = None) -> None:
    """Run the node (:func:`cgags_ros.ros.node.main`), its threads set up first."""
    quiet_idle_threads()  # before the node imports numpy; its registration process inherits it
    from .ros.node import main as run_node

    run_node(args)


if __name__ == '__main__':
    main()
