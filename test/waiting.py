"""Helpers of the tests: waiting for conditions, ROS contexts, node processes, the kitchen map."""

import contextlib
import signal
import subprocess
import threading
import time

import pytest


def wait_for(predicate, timeout, what, detail=None):
    """
    Poll until ``predicate()`` is truthy and return its value.

    Fail after ``timeout`` seconds instead of hanging, with ``detail()`` (e.g. the node's
    counters and last rejection reason) in the message.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    pytest.fail(f'timed out after {timeout} s waiting for {what}'
                + (f'; node state: {detail()}' if detail else ''))


def stop_process(proc, log) -> str:
    """SIGTERM a node process (SIGKILL after 20 s), wait for it; return its log."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    log.seek(0)
    out = log.read()
    log.close()
    return out


@contextlib.contextmanager
def spun_context(domain_id, make_io):
    """
    Yield (context, executor, io): an rclpy context on ``domain_id`` spun on a thread.

    A multi-threaded executor, as the node's own ``main`` spins: a ~/relocalize call waits
    for a registration on one thread while the topics go on on the others.

    ``io = make_io(context)`` is the test's own node wrapper (publishers, recorders); its
    ``node`` is added to the executor. Everything is shut down on exit.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import MultiThreadedExecutor

    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    io = make_io(context)
    executor = MultiThreadedExecutor(num_threads=4, context=context)
    executor.add_node(io.node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield context, executor, io
    finally:
        executor.shutdown(timeout_sec=2.0)
        io.node.destroy_node()
        context.try_shutdown()
        thread.join(timeout=5.0)


def merged_kitchen_map(data_dir, folder):
    """
    Write the redkitchen fragments 0 and 4 merged with their ground truth to ``folder``.

    :returns: (map path, merged points, (fragment 6, its GT to 0), (fragment 4, its GT)).
    """
    import numpy as np

    from cgags_ros.datasets.gt_pairs import find_pair
    from cgags_ros.geometry import apply_transform
    from cgags_ros.io.clouds import read_cloud

    base = data_dir / 'indoor_3dmatch'
    f4, f0, T40 = find_pair(base / 'gt_pairs.txt', 'cloud_bin_4.ply', 'cloud_bin_0.ply')
    frag4 = read_cloud(f4)
    merged = np.vstack([read_cloud(f0), apply_transform(T40, frag4)])
    path = folder / 'kitchen.npy'
    np.save(path, merged)
    demo = base / 'geotransformer_demo'
    return path, merged, (np.load(demo / 'src.npy'), np.load(demo / 'gt.npy')), (frag4, T40)
