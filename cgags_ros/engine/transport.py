"""
The Fast DDS profile for LiDAR-size clouds, and the one place that turns it on.

Fast DDS as shipped with Jazzy loses most best-effort clouds of more than about half a
megabyte between two processes; ``config/fastdds_large_data.xml`` (installed in
``share/cgags_ros/config/``) fixes it on one host when the PUBLISHING process loads it, so
a LiDAR driver's shell needs it too (docs/transport.md). Every process of this package
that takes part in DDS (the node, the live replay's player) calls
:func:`use_large_data_profile` before ``rclpy.init``.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
from typing import MutableMapping

PROFILE_FILE = 'fastdds_large_data.xml'
# The variable Fast DDS 2.14 (Jazzy's) reads; Fast DDS 3 reads FASTDDS_DEFAULT_PROFILES_FILE.
PROFILE_VARIABLE = 'FASTRTPS_DEFAULT_PROFILES_FILE'
BUILTIN_VARIABLE = 'FASTDDS_BUILTIN_TRANSPORTS'
PACKAGE = 'cgags_ros'


def profile_path() -> Path | None:
    """Return the shipped profile: the source tree's ``config/``, else the installed share."""
    here = Path(__file__).resolve().parents[2] / 'config' / PROFILE_FILE
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import (get_package_share_directory,
                                                 PackageNotFoundError)
        try:
            shared = Path(get_package_share_directory(PACKAGE)) / 'config' / PROFILE_FILE
            if shared.is_file():
                return shared
        except PackageNotFoundError:
            pass
    except ImportError:
        pass
    prefixed = Path(sys.prefix) / 'share' / PACKAGE / 'config' / PROFILE_FILE
    return prefixed if prefixed.is_file() else None


def use_large_data_profile(environ: MutableMapping[str, str] = os.environ) -> str:
    """
    Make Fast DDS load the shipped profile, unless the user chose the transports.

    The user's choice wins: a set ``FASTRTPS_DEFAULT_PROFILES_FILE`` (an empty one means
    Fast DDS's defaults; it is removed, since Fast DDS logs an error for an empty path), a
    set ``FASTDDS_BUILTIN_TRANSPORTS``, or an ``RMW_IMPLEMENTATION`` other than Fast DDS.
    Call before ``rclpy.init``: Fast DDS reads the variable once per process.

    :returns: the profile Fast DDS will load ('' for none).
    """
    if PROFILE_VARIABLE in environ:
        if not environ[PROFILE_VARIABLE]:
            del environ[PROFILE_VARIABLE]
            return ''
        return environ[PROFILE_VARIABLE]
    if environ.get(BUILTIN_VARIABLE) or 'fastrtps' not in environ.get(
            'RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp'):
        return ''
    path = profile_path()
    if path is None:
        return ''
    environ[PROFILE_VARIABLE] = str(path)
    return str(path)


def user_line() -> str:
    """Return the one line a publisher's shell needs (the fix needs both processes)."""
    path = profile_path()
    return f'export {PROFILE_VARIABLE}={path or "<prefix>/share/cgags_ros/config/" + PROFILE_FILE}'
