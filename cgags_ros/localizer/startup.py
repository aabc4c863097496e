"""
Starting registration: what a lifecycle node's configure transition waits for.

ROS-free. :func:`start_registration` returns once a pair can be registered at once: the
registration process (:class:`~cgags_ros.runtime.supervisor.Supervisor`) has
finished its warm-up (the pipeline imported, its numba code compiled or read from its
cache, one small registration) and, with ``map.file``, the map's features are prepared
where the pipeline runs (:class:`~.map_target.MapTarget`). Otherwise it raises
:class:`~.interface.StartFailed` with the reason and leaves nothing running, so that
configure fails and the node stays unconfigured.

Every wait is bounded when the pipeline runs in its own process (``worker.registration_timeout``
> 0, the default): the warm-up by :data:`~cgags_ros.runtime.supervisor.WARM_UP_LIMIT_S`, the
map load by ``map.load_timeout``. In the node's own process (``worker.registration_timeout`` 0, and
``mode: calibrate``) a Python call cannot be interrupted: the import, the warm-up and the
map load end when they end.
"""

from __future__ import annotations

from typing import Any, Callable

from .interface import MapCloud, StartFailed
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..runtime.session import ChildSession, RegisterFn, warm_up
from ..runtime.supervisor import Supervisor


def start_registration(pipeline_cfg: PipelineConfig, cfg: NodeConfig, in_process: bool,
                       register_fn: RegisterFn | None, map_target: Any,
                       log: Callable[[str, str], None]
                       ) -> tuple[Any, Supervisor | None, MapCloud | None]:
    """
    Start what registers pairs and wait until it can (see the module doc).

    :param in_process: run the pipeline in this process even if ``worker.registration_timeout``
        asks for a registration process (the calibrate mode does).
    :param register_fn: replaces ``register_clouds`` in every job (tests of the plumbing
        only): the jobs then run in this process.
    :param map_target: the :class:`~.map_target.MapTarget` to load, or None.
    :returns: (what runs a job: the supervised process or a ``ChildSession`` of this
        process; the supervised process or None; the map as a target or None).
    :raises StartFailed: the process did not warm up (it died, failed or ran past its
        limit), the pipeline failed to load, or the map cannot be used.
    """
    registration = None
    try:
        if register_fn is not None:
            runner: Any = ChildSession(register_fn)
        elif cfg.worker.registration_timeout > 0 and not in_process:
            registration = runner = Supervisor(cfg.worker.registration_timeout)
            registration.wait_ready()
        else:  # import the pipeline (and Open3D) now, so the first pair is not slowed by it
            warm_up()
            runner = ChildSession()
        target = None if map_target is None else map_target.load(runner, pipeline_cfg, cfg, log)
    except BaseException as exc:  # noqa: BLE001 - even Ctrl-C leaves no process behind
        if registration is not None:
            registration.close()
        if isinstance(exc, StartFailed) or not isinstance(exc, Exception):
            raise
        reason = (str(exc) if isinstance(exc, CgagsError)
                  else f'the registration pipeline failed to load: {exc!r}')
        raise StartFailed(reason) from exc
    return runner, registration, target
