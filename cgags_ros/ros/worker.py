"""
The registration worker: ``register_clouds`` in a child process, with a time limit.

ROS-free by itself, but it exists for the node: a pathological input that makes the
pipeline loop (or crash natively) costs one pair, not the node.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
import multiprocessing
from typing import Any, Callable

import numpy as np

from ..config.pipeline import PipelineConfig
from ..errors import CgagsError

RegisterFn = Callable[..., Any]  # register_clouds(source, target, *, config) -> PipelineResult

_WARM_UP_LIMIT_S = 120.0  # starting a registration process (imports Open3D) may take this


class RegistrationTimeout(CgagsError):
    """A registration ran past ``registration_timeout`` and its process was killed."""


_child_target: np.ndarray | None = None  # in the registration process: the last target


class _TargetNotHeld(Exception):
    """The registration process holds no target (it was restarted): send it again."""


def _register_in_child(source: np.ndarray, target: np.ndarray | None, *,
                       config: PipelineConfig) -> Any:
    """
    Run ``register_clouds`` in the registration process.

    ``target=None`` reuses the target sent last, so an unchanged (latched) target crosses
    the pipe once, not every pair.
    """
    global _child_target
    from ..pipeline import register_clouds  # in the child: the parent needs no Open3D

    if target is not None:
        _child_target = target
    elif _child_target is None:
        raise _TargetNotHeld()
    return register_clouds(source, _child_target, config=config)


def _warm_up_in_child() -> Any:
    from ..pipeline import warm_up

    return warm_up()


class IsolatedRegistration:
    """
    Runs ``register_clouds`` in one spawned child process with a time limit.

    A pathological input that makes the pipeline loop (or crash natively) costs one pair:
    the child is killed and a fresh one started. Spawn, not fork: forking a process that
    runs DDS threads is unsafe. Results and typed errors come back pickled. The child keeps
    the last target: a target that is the same array object as the previous call's is not
    sent again (the node never writes to a decoded cloud).
    """

    def __init__(self, timeout_s: float):
        self.timeout_s = timeout_s
        self._pool: Any = None
        self._closed = False
        self._sent_target: np.ndarray | None = None  # what the child holds (by identity)
        self._start()

    def _start(self) -> None:
        self._fn = _register_in_child
        self._sent_target = None
        self._pool = ProcessPoolExecutor(max_workers=1,
                                         mp_context=multiprocessing.get_context('spawn'))
        # Warm-up: the child imports the pipeline (Open3D) and runs every stage once on a
        # small synthetic pair, so no start-up cost is counted against a real pair's limit.
        self._warm = self._pool.submit(_warm_up_in_child)

    def __call__(self, source: np.ndarray, target: np.ndarray, *, config: PipelineConfig) -> Any:
        if self._pool is None:
            raise RegistrationTimeout('the registration process is shut down')
        if self._warm is not None:
            try:
                self._warm.result(timeout=_WARM_UP_LIMIT_S)
            except Exception:  # noqa: BLE001 - a failed warm-up shows again on the real pair
                pass
            self._warm = None
        held = target is self._sent_target
        # Only a completed call proves the child holds this target; after any failure it
        # is sent again.
        self._sent_target = None
        future = self._pool.submit(self._fn, source, None if held else target, config=config)
        try:
            result = future.result(timeout=self.timeout_s)
            self._sent_target = target
            return result
        except _TargetNotHeld:  # not expected (a restart forgets what was sent); resend
            return self(source, target, config=config)
        except FutureTimeout:
            self.restart()
            raise RegistrationTimeout(
                f'registration took longer than registration_timeout = {self.timeout_s:g} s; '
                'its process was restarted') from None
        except BrokenProcessPool:
            self.restart()
            raise RegistrationTimeout('the registration process died; restarted') from None

    def restart(self) -> None:
        self._kill()
        if not self._closed:
            self._start()

    def close(self) -> None:
        self._closed = True
        # Wait for the pool's manager thread: one still running at interpreter exit races
        # concurrent.futures' atexit hook, which then prints "OSError: handle is closed".
        # The child is killed first, so this returns at once.
        self._kill(wait=True)

    def _kill(self, wait: bool = False) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        # ProcessPoolExecutor cannot cancel a running call: stop its process directly.
        for proc in list(getattr(pool, '_processes', {}).values()):
            proc.kill()
        pool.shutdown(wait=wait, cancel_futures=True)


def load_pipeline() -> RegisterFn:
    """Import the pipeline (and Open3D) now and warm it up; return ``register_clouds``."""
    from ..pipeline import register_clouds, warm_up

    warm_up()  # pay Open3D's start-up now rather than on the first pair
    return register_clouds
