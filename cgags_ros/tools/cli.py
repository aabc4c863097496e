"""The error helpers of the command-line tools: library and usage errors as one line, exit 2."""

from __future__ import annotations

import argparse
import sys
from typing import Callable

from ..errors import CgagsError

EXIT_ERROR = 2  # bad input or options: nothing (more) was done
EXIT_INTERRUPTED = 130


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr and exit 2."""

    def error(self, message: str):
        """Exit with one line on stderr (argparse would also print the whole usage)."""
        self.exit(EXIT_ERROR, f'{self.prog}: error: {message} (see --help)\n')


def error_line(prog: str, exc: BaseException, what: str = '') -> str:
    """
    Return ``PROG: [WHAT: ]error: [CODE: ]MESSAGE`` with the message folded onto one line.

    ``CODE`` is a :class:`~cgags_ros.errors.CgagsError`'s refusal code (docs/refusals.md).
    """
    where = f'{what}: ' if what else ''
    code = f'{exc.code.value}: ' if isinstance(exc, CgagsError) else ''
    return f"{prog}: {where}error: {code}{' '.join(str(exc).split())}"


def run_cli(prog: str, body: Callable[[], int]) -> int:
    """Run ``body``; a CgagsError becomes one line on stderr and exit 2, Ctrl-C exit 130."""
    try:
        return body()
    except CgagsError as exc:
        print(error_line(prog, exc), file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return EXIT_INTERRUPTED
