"""
The registration process's side of the pipe: what it runs, and how a job's clouds travel.

:func:`serve` runs in the spawned process: it warms up, then answers each job with its
:class:`~.session.ChildSession`. :class:`Child` is the parent's handle on one such process:
its pipe, its warm-up, whether it still runs. :func:`spill` writes a job's clouds to files
(see :mod:`.supervisor` for why) and :func:`unspill` reads them back in the process.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import signal
import tempfile
from typing import Any, Callable

import numpy as np

from .jobs import Job
from .procfs import running
from .session import ChildSession, warm_up
from ..errors import CgagsError
from ..parallel import quiet_idle_threads


class ChildDied(Exception):
    """The process's pipe ended: it is gone."""


@dataclasses.dataclass(frozen=True)
class Spilled:
    """An array a job carries, written to ``path`` (``.npy``) instead of the pipe."""

    path: str


CLOUDS = ('source', 'target')  # the fields of a job that may hold a cloud


def spill(job: Job, folder: str) -> tuple[Job, list[str]]:
    """Return ``job`` with its clouds written to files in ``folder``, and those files."""
    changes, paths = {}, []
    for name in CLOUDS:
        value = getattr(job, name, None)
        if isinstance(value, np.ndarray):
            fd, path = tempfile.mkstemp(suffix='.npy', prefix='cgags-job-', dir=folder)
            with os.fdopen(fd, 'wb') as f:
                np.save(f, value, allow_pickle=False)
            changes[name] = Spilled(path)
            paths.append(path)
    return (dataclasses.replace(job, **changes) if changes else job), paths


def unspill(job: Any) -> Any:
    """Return ``job`` with its spilled clouds read back (in the process)."""
    changes = {name: np.load(value.path, allow_pickle=False) for name in CLOUDS
               if isinstance(value := getattr(job, name, None), Spilled)}
    return dataclasses.replace(job, **changes) if changes else job


def spill_folder() -> str:
    """Return where spilled clouds go: ``/dev/shm`` (memory) when writable, else the temp dir."""
    shm = '/dev/shm'
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK) else tempfile.gettempdir()


def serve(conn: Any, niceness: int) -> None:
    """
    Run in the process: warm up and answer, then run each job of the pipe and answer it.

    Every answer is ``(ok, value)``: the job's answer or the exception it raised. The parent
    decides when the process ends (it kills it, or closes the pipe), so a Ctrl-C meant for
    the parent's terminal does not end a registration here.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if niceness:
        os.nice(niceness)
    session = ChildSession()
    # Warm-up: the pipeline imported (Open3D) and every stage run once on a small synthetic
    # pair, so that no start-up cost is counted against a real job's limit.
    ok, value = _run(warm_up)
    answer = _pickled(ok, None if ok else value)
    while True:
        try:
            conn.send_bytes(answer)
            job = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone or closed the pipe
        answer = _pickled(*_run(lambda: session.run(unspill(job))))


def _run(fn: Callable[[], Any]) -> tuple[bool, Any]:
    try:
        return True, fn()
    except Exception as exc:  # noqa: BLE001 - sent back, raised in the parent
        return False, exc


def _pickled(ok: bool, value: Any) -> bytes:
    """Return the answer ``(ok, value)`` as bytes for the pipe, or an error that pickles."""
    try:
        return pickle.dumps((ok, value), protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - an answer that does not pickle
        return pickle.dumps((False, CgagsError(
            f'the registration process cannot send back {value!r}: {exc!r}')))


class Child:
    """One spawned process and its pipe; ``warm`` once its warm-up answered."""

    def __init__(self, name: str, niceness: int) -> None:
        # Spawn, not fork: forking a process that runs DDS threads is unsafe. The process
        # inherits this environment and loads numpy before any code of ours runs in it.
        quiet_idle_threads()
        context = multiprocessing.get_context('spawn')
        self.conn, child_end = context.Pipe()
        self.process = context.Process(target=serve, args=(child_end, niceness), name=name,
                                       daemon=True)
        self.process.start()
        child_end.close()  # the process's copy alone keeps it open: its death ends the pipe
        self.warm = False
        self.warm_error: BaseException | None = None

    @property
    def alive(self) -> bool:
        """Tell whether the process still runs (by pid: a zombie counts as dead)."""
        return running(self.process.pid)

    def receive(self, timeout_s: float | None) -> tuple[bool, Any] | None:
        """Return the next answer ``(ok, value)``, None past ``timeout_s`` (or ChildDied)."""
        try:
            if not self.conn.poll(timeout_s):
                return None
            return self.conn.recv()
        except (EOFError, OSError):
            raise ChildDied() from None
        except Exception as exc:  # noqa: BLE001 - an answer that does not unpickle
            return False, CgagsError(f'unreadable answer of the registration process: {exc!r}')

    def wait_warm(self, timeout_s: float | None) -> bool:
        """Take the warm-up's answer if it came within ``timeout_s``; tell whether warm."""
        if not self.warm:
            answer = self.receive(timeout_s)
            if answer is not None:
                self.warm, self.warm_error = True, None if answer[0] else answer[1]
        return self.warm

    def kill(self) -> None:
        """End the process now and release the pipe."""
        self.process.kill()
        self.process.join(5.0)
        self.conn.close()


def remove_files(paths: list[str]) -> None:
    for path in paths:
        try:
            os.remove(path)
        except OSError:
            pass  # already gone
