"""Helpers of the DDS tests: wait for a condition (fail with context, never hang), stop a node."""

import signal
import subprocess
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
