"""What Linux's /proc says about a process: its resident memory, whether it still runs."""

from __future__ import annotations

import os


def rss_mb(pid: int | None = None) -> float | None:
    """Return the resident memory of process ``pid`` (default: this one) in MB, if known."""
    try:
        with open(f"/proc/{pid or 'self'}/statm", encoding='ascii') as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None  # not Linux, or the process is gone
    return pages * os.sysconf('SC_PAGE_SIZE') / 1e6


def running(pid: int) -> bool:
    """Tell whether process ``pid`` exists and is not a zombie (dead, not yet reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii') as f:
            return f.read().rsplit(')', 1)[1].split()[0] not in ('Z', 'X')
    except (OSError, IndexError):
        return True  # no /proc: the signal test is all there is
