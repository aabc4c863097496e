"""Frames for ``cgags-calibrate``: pairs of cloud files, or pairs of bag messages in time."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

from .replay_common import read_bag_contents
from ..calibration import Frame
from ..errors import InvalidInputError
from ..io.clouds import read_cloud


def file_frames(parents: Sequence[Path], children: Sequence[Path]) -> Iterator[Frame]:
    """Yield frame k = (parents[k], children[k]), read when taken."""
    for parent, child in zip(parents, children):
        yield Frame(read_cloud(parent), read_cloud(child), f'{parent.name} + {child.name}')


def bag_frames(path: Path, parent_topic: str, child_topic: str, max_offset: float,
               min_interval: float) -> tuple[Iterator[Frame], str, str]:
    """
    Return (frames of the bag, parent frame id, child frame id).

    Each parent message is paired with the child message nearest in stamp, when they
    differ by at most ``max_offset`` seconds, each child used once (:func:`pair_stamps`);
    a pair is taken when its parent stamp is at least ``min_interval`` seconds after the
    last one taken.
    """
    if max_offset < 0 or min_interval < 0:
        raise InvalidInputError('--max-time-offset and --min-interval must be >= 0')
    contents = read_bag_contents(path, child_topic, parent_topic, None)
    clouds = [c for c in contents.clouds if c.xyz is not None and c.stamp_ns is not None]
    parents = [c for c in clouds if c.role == 'target']
    children = [c for c in clouds if c.role == 'source']
    parent_id = parents[0].frame_id if parents else ''
    child_id = children[0].frame_id if children else ''
    pairs = pair_stamps([c.stamp_ns for c in parents], [c.stamp_ns for c in children],
                        int(round(max_offset * 1e9)))

    def frames() -> Iterator[Frame]:
        last = None
        for i, j in pairs:
            parent, child = parents[i], children[j]
            if last is not None and parent.stamp_ns - last < min_interval * 1e9:
                continue
            last = parent.stamp_ns
            yield Frame(parent.xyz, child.xyz, f'{parent.stamp_ns * 1e-9:.3f} s',
                        parent.stamp_ns, child.stamp_ns)

    return frames(), parent_id, child_id


def pair_stamps(parents: Sequence[int], children: Sequence[int],
                slop_ns: int) -> list[tuple[int, int]]:
    """
    Return (parent index, child index) pairs, in parent order.

    Closest stamps first: every (parent, child) within ``slop_ns`` nanoseconds, by
    increasing |difference|, is taken unless either message is already paired. A whole bag
    is at hand, so no pair waits for messages to come (the node's pairing must).
    """
    close = sorted((abs(p - c), i, j) for i, p in enumerate(parents)
                   for j, c in enumerate(children) if abs(p - c) <= slop_ns)
    used_p, used_c, out = set(), set(), []
    for _, i, j in close:
        if i not in used_p and j not in used_c:
            used_p.add(i)
            used_c.add(j)
            out.append((i, j))
    return sorted(out)
