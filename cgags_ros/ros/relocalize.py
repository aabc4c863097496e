"""
On-demand relocalization: the ``~/relocalize`` service (std_srvs/srv/Trigger).

In ``mode: on_demand`` the node registers nothing until the service is called. A call
then takes the latest scan if it was received within ``max_scan_age`` before the call, or
else waits (at most ``relocalize_timeout``) for the next one; the registration worker
answers it with ``success`` (a confident pose: valid, not ambiguous, every quality guard
of the initial pose passed) and a one-line summary (pose, inliers, best/runner-up ratio,
or why it failed).

The service is served by a small helper node (``<node>_relocalize``, same context) spun on
its own thread, under the main node's name (``/<node>/relocalize``): its callback blocks
until the worker answers, and so never holds up the main node's executor (rclpy would
busy-poll an awaiting coroutine callback).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from std_srvs.srv import Trigger


class _Request:
    __slots__ = ('called', 'deadline', 'done', 'answer')

    def __init__(self, called: float, deadline: float):
        self.called, self.deadline = called, deadline
        self.done = threading.Event()
        self.answer: tuple[bool, str] = (False, 'not answered')


class Relocalizer:
    """Pending ``~/relocalize`` calls, answered by the registration worker."""

    def __init__(self, node: Any, timeout_s: float):
        self.timeout_s = timeout_s
        self.counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._pending: list[_Request] = []
        self._wake = threading.Event()
        name = node.get_fully_qualified_name()
        self._helper = rclpy.create_node(f'{node.get_name()}_relocalize',
                                         namespace=node.get_namespace(), context=node.context,
                                         start_parameter_services=False)
        self._helper.create_service(Trigger, f'{name}/relocalize', self._on_call)
        self._executor = SingleThreadedExecutor(context=node.context)
        self._executor.add_node(self._helper)
        self._thread = threading.Thread(target=self._spin, name='relocalize_service',
                                        daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception:  # noqa: BLE001 - the context was shut down under the executor
            pass

    def _on_call(self, request: Any, response: Any) -> Any:
        now = time.monotonic()
        req = _Request(now, now + self.timeout_s)
        with self._lock:
            self.counts['calls'] += 1
            self._pending.append(req)
        self._wake.set()
        # The worker answers, or expire() does at the deadline; the margin covers a
        # registration that started just before the deadline.
        req.done.wait(self.timeout_s + 3600.0)
        response.success, response.message = req.answer
        return response

    def waiting(self) -> float | None:
        """Return the monotonic time of the oldest pending call, or None when there is none."""
        with self._lock:
            return self._pending[0].called if self._pending else None

    def wait(self, timeout: float) -> None:
        """Sleep until a call arrives or ``timeout`` seconds pass."""
        self._wake.wait(timeout)
        self._wake.clear()

    def expire(self, busy: bool = False) -> None:
        """Answer failure to calls past their deadline (not while a scan is registered)."""
        if busy:
            return
        now = time.monotonic()
        with self._lock:
            late = [r for r in self._pending if r.deadline <= now]
            self._pending = [r for r in self._pending if r.deadline > now]
        for req in late:
            self._finish(req, False, f'no scan received within relocalize_timeout = '
                         f'{self.timeout_s:g} s', 'no_scan')

    def answer(self, success: bool, message: str, reason: str) -> int:
        """Answer every pending call with one result; return how many were answered."""
        with self._lock:
            answered, self._pending = self._pending, []
        for req in answered:
            self._finish(req, success, message, reason)
        return len(answered)

    def _finish(self, req: _Request, success: bool, message: str, reason: str) -> None:
        with self._lock:
            self.counts['succeeded' if success else f'failed.{reason}'] += 1
        req.answer = (success, message)
        req.done.set()

    def statistics(self) -> dict[str, int]:
        """Return ``relocalize.*`` counters for /diagnostics."""
        with self._lock:
            return {f'relocalize.{k}': v for k, v in sorted(self.counts.items())}

    def close(self) -> None:
        """Answer pending calls (shutting down) and stop the helper node."""
        self.answer(False, 'the node is shutting down', 'shutdown')
        self._executor.shutdown(timeout_sec=2.0)
        self._helper.destroy_node()
        self._thread.join(timeout=2.0)
