"""
Relocalization requests: what ``~/relocalize`` and ``reinitialize_global_localization`` ask.

ROS-free. A request is answered by the engine thread with the next registration
(in ``mode: on_demand`` it is what makes the engine thread register at all): ``success`` for a
confident pose (valid, not ambiguous, every quality guard of the initial pose passed) and a
one-line summary (pose, inliers, best/runner-up ratio), or, on failure, a line that
starts with the refusal's code (``ambiguous: not localized: ...``, :func:`not_localized`).
In on_demand mode a request takes the latest scan if it was received within
``relocalization.max_scan_age`` before the request, or else waits for the next one; a
request no registration answered within its timeout (``relocalization.timeout``) fails.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from typing import Callable

import numpy as np

from ..geometry import rpy
from ..pipeline.result import PipelineResult
from ..refusal import Refusal, RefusalCode

Answered = Callable[[bool, str], None]  # called with (success, message) once answered


class Request:
    """
    One pending request: when it was made (monotonic s), its deadline, its answer.

    ``hint``: where to look, opaque here (the node's pose hint): the scans that answer the
    request carry it, and it ends with the request.
    """

    __slots__ = ('called', 'deadline', 'answer', 'on_answer', 'hint')

    def __init__(self, called: float, deadline: float, on_answer: Answered | None = None,
                 hint: object = None):
        self.called, self.deadline, self.hint = called, deadline, hint
        self.answer: tuple[bool, str] = (False, 'not answered')
        self.on_answer = on_answer


class ServiceCalls:
    """
    Pending relocalization requests, answered by the engine thread.

    Two threads write: the node's executor adds requests (a service call) and fails them
    (a deactivation), the engine thread answers and expires them; the pending list and the counts
    change under one lock. The executor wakes the engine thread's :meth:`wait` with an event.
    """

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._pending: list[Request] = []
        self._wake = threading.Event()

    def add(self, timeout_s: float, on_answer: Answered | None = None,
            hint: object = None) -> Request:
        """Queue a request that fails unless answered within ``timeout_s`` seconds."""
        now = time.monotonic()
        req = Request(now, now + timeout_s, on_answer, hint)
        with self._lock:
            self.counts['calls'] += 1
            self._pending.append(req)
        self._wake.set()
        return req

    def refuse(self, refusal: Refusal) -> tuple[bool, str]:
        """Count a request answered at once with failure (e.g. the node is inactive)."""
        with self._lock:
            self.counts['calls'] += 1
            self.counts[f'failed.{refusal.code.value}'] += 1
        return False, not_localized(refusal)

    def waiting(self) -> float | None:
        """Return the monotonic time of the oldest pending request, or None when none is."""
        with self._lock:
            return self._pending[0].called if self._pending else None

    def hint(self) -> object:
        """Return the hint of the newest pending request that has one (None: none has)."""
        with self._lock:
            return next((r.hint for r in reversed(self._pending) if r.hint is not None), None)

    def wait(self, timeout: float) -> None:
        """Sleep until a request arrives or ``timeout`` seconds pass."""
        self._wake.wait(timeout)
        self._wake.clear()

    def wake(self) -> None:
        """End a :meth:`wait` at once (shutting down)."""
        self._wake.set()

    def expire(self, why: Refusal | None = None) -> int:
        """
        Answer failure to the requests past their deadline; return how many.

        ``why``: the refusal of a relocalization over several scans still in progress
        (None: no scan was received for them).
        """
        now = time.monotonic()
        with self._lock:
            late = [r for r in self._pending if r.deadline <= now]
            self._pending = [r for r in self._pending if r.deadline > now]
        for req in late:
            timeout = req.deadline - req.called
            refusal = why or Refusal(RefusalCode.NO_SCAN, 'no scan received within '
                                     f'relocalization.timeout = {timeout:g} s')
            self._finish(req, not_localized(refusal), refusal)
        return len(late)

    def answer(self, message: str, refusal: Refusal | None = None) -> int:
        """
        Answer every pending request with one result; return how many were answered.

        ``refusal`` None: success; else failure, counted by its code.
        """
        with self._lock:
            answered, self._pending = self._pending, []
        for req in answered:
            self._finish(req, message, refusal)
        return len(answered)

    def fail(self, refusal: Refusal) -> int:
        """Answer every pending request with failure: :func:`not_localized`."""
        return self.answer(not_localized(refusal), refusal)

    def _finish(self, req: Request, message: str, refusal: Refusal | None) -> None:
        success = refusal is None
        with self._lock:
            self.counts['succeeded' if success else f'failed.{refusal.code.value}'] += 1
        req.answer = (success, message)
        if req.on_answer is not None:
            req.on_answer(success, message)

    def statistics(self) -> dict[str, int]:
        """Return ``relocalize.*`` counters for /diagnostics."""
        with self._lock:
            return {f'relocalize.{k}': v for k, v in sorted(self.counts.items())}


def not_localized(refusal: Refusal) -> str:
    """Return the answer of a failed request: the refusal's code first, then why."""
    return f'{refusal.code.value}: not localized: {refusal.message}'


def summary_line(result: PipelineResult, T: np.ndarray, refusal: Refusal | None,
                 published: bool, why: str) -> str:
    """Return the one-line answer of a request: pose, inliers, ratio, or why not."""
    scores = (f'{result.num_inliers} inliers, best/runner-up {result.runner_up_ratio:.2f}, '
              f'fitness {result.fitness:.3f}')
    if refusal is not None:
        return f'{not_localized(refusal)}; {scores}'
    return localized(T, scores, published, why)


def localized(T: np.ndarray, details: str, published: bool, why: str) -> str:
    """Return the answer of a successful request: the pose (x y z, yaw), ``details``, publish."""
    x, y, z = (float(v) for v in T[:3, 3])
    pose = f'x {x:.3f} y {y:.3f} z {z:.3f} m, yaw {math.degrees(rpy(T)[2]):.1f} deg'
    return (f'localized: {pose}; {details}; '
            + ('initial pose published' if published else f'initial pose not published: {why}'))


def stale_scan(called: float | None, receipt_ns: int, max_scan_age: float) -> Refusal | None:
    """
    Return why a scan is too old for the pending on-demand request, or None.

    :param called: when the pending request was made (monotonic seconds), None when none.
    :param receipt_ns: when the scan was received (monotonic nanoseconds).
    """
    if called is None:
        return None
    age = called - receipt_ns * 1e-9
    if age <= max_scan_age:
        return None
    return Refusal(RefusalCode.STALE, (
        f'on_demand: the latest scan was received {age:.2f} s before the relocalization '
        f'request (> relocalization.max_scan_age {max_scan_age:g} s); waiting for the '
        'next one'))
