r"""
Fragments whose 3DMatch ground-truth pose the trusted estimates contradict; the pairs in doubt.

A pair's truth is ``inv(P_i) P_j`` of two fragment poses (:mod:`bench.datasets.threedmatch`):
one pose off makes every pair holding that fragment judged against a wrong truth. Each
estimate the pipeline trusted (``valid``, both lists of ``bench/studies/loso_trust.py measure``'s
records), ``T_ij`` (fragment j into fragment i), implies the world pose ``P_i T_ij`` of j and
``P_j inv(T_ij)`` of i. Per fragment, the implied pose with the most others within AGREE_DEG
and AGREE_M (the medoid) and those near it form the largest agreeing group, whose consensus
is the mean translation and the chordal mean rotation. A fragment is doubtful when the group
holds at least MIN_PARTNERS distinct partners and the consensus lies more than DOUBT_DEG or
DOUBT_M from the benchmark's pose. The evidence of doubtful partners is then left out and
the check repeated until the doubtful set stops changing (at most MAX_ROUNDS rounds), so
that a wrong pose, or a segment of them, casts no doubt on its partners.

- AGREE_DEG, AGREE_M: about twice the median error of a right estimate against the truth,
  so that a fragment's right estimates fall in one group and a wrong one does not.
- DOUBT_DEG: a third of the benchmark's 15 deg success limit, an offset that flips a pair's
  verdict together with an estimate's own error. DOUBT_M: half its 30 cm limit, so that it
  stays above AGREE_M and the spread of one agreeing group alone never raises doubt.
- MIN_PARTNERS: fewer agreeing partners are too easily one shared mistake (a repeated
  structure seen from neighbouring fragments).

Pairs in doubt are those (either list) holding a doubtful fragment; the output gives each
estimate's error against the corrected truth ``inv(C_i) C_j`` (C: the consensus pose of a
doubtful fragment, P otherwise) beside the benchmark's verdict. A study leaves those pairs
out with :func:`doubtful_fragments` and :func:`in_doubt`.

Run by hand from the repository root (no registration: seconds)::

    .venv/bin/python -m bench.truth_check [out/loso_trust/records.jsonl ...] \
        [--evidence out/truth_check/settled.jsonl] [--root <shared data>/3dmatch_benchmark] \
        [--output out/truth_check/doubtful]

``--evidence``: records checked on their own as well, here the truths settled by
:mod:`bench.truth_settle` (ICP on each pair started from its benchmark pose: evidence that
does not depend on our estimator, for fragments with too few trusted estimates); a fragment
either check doubts is doubtful.

It writes ``<output>.md`` (the table of doubtful fragments, also printed) and
``<output>.json`` (every fragment's check, the doubtful ones per scene with their consensus
pose, the pairs in doubt with both errors) under the git-ignored ``out/``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Iterable, Mapping

from bench.common import argument_parser, markdown_table, write_json, write_text
from bench.datasets import threedmatch as tdm
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np

AGREE_DEG = 3.0
AGREE_M = 0.1
DOUBT_DEG = 5.0
DOUBT_M = 0.15
MIN_PARTNERS = 4
MAX_ROUNDS = 4
MAX_RE_DEG, MAX_TE_M = tdm.MAX_RE_DEG, tdm.MAX_TE_M  # 3DMatch's registration recall

Poses = Mapping[str, Mapping[int, np.ndarray]]


@dataclasses.dataclass
class FragmentCheck:
    """
    One fragment's benchmark pose against the poses its partners' estimates imply.

    :ivar scene, fragment: the scene folder and fragment index ``k``.
    :ivar partners: distinct partners with a trusted estimate (after the last round's
        exclusions); ``group``: distinct partners in the largest agreeing group.
    :ivar spread_deg, spread_m: the group's largest deviation from the consensus.
    :ivar offset_deg, offset_m: the benchmark pose ``P_k`` from the consensus.
    :ivar consensus: 4x4 world pose (``p_world = C p_fragment``, metres).
    :ivar doubtful: the group is large enough and the offset above DOUBT_DEG or DOUBT_M.
    :ivar evidence: ``estimates`` (the trusted estimates) or ``settled`` (the truths settled
        by :mod:`bench.truth_settle`).
    """

    scene: str
    fragment: int
    partners: int
    group: int
    spread_deg: float
    spread_m: float
    offset_deg: float
    offset_m: float
    consensus: np.ndarray
    doubtful: bool
    evidence: str = 'estimates'

    def as_dict(self) -> dict:
        """Return the check as JSON-ready values."""
        return {**dataclasses.asdict(self), 'consensus': self.consensus.tolist()}


def read_records(paths: Iterable[str | Path]) -> list[dict]:
    """
    Return the records of JSONL files, one per (benchmark, scene, target, source), last kept.

    An unterminated last line is a record still being written and is skipped.
    """
    records = {}
    for path in paths:
        text = Path(path).read_text(encoding='utf-8')
        lines = text.splitlines() if text.endswith('\n') else text.splitlines()[:-1]
        for line in filter(str.strip, lines):
            r = json.loads(line)
            records[pair_key(r)] = r
    return list(records.values())


def pair_key(record: Mapping) -> tuple[str, str, int, int]:
    """Return ``(benchmark, scene, target, source)`` of a record."""
    return record['benchmark'], record['scene'], int(record['target']), int(record['source'])


def load_poses(root: str | Path, scenes: Iterable[str]) -> dict[str, dict[int, np.ndarray]]:
    """Return the benchmark's fragment poses of ``scenes``, each projected onto a rigid one."""
    return {s: {k: tdm.nearest_rigid(P) for k, P in tdm.fragment_poses(root, s).items()}
            for s in sorted(set(scenes))}


def _rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Return the angles (degrees) between rotations (..., 3, 3), broadcast."""
    c = (np.einsum('...ij,...ij->...', Ra, Rb) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def consensus(implied: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """
    Return the largest agreeing group of implied poses (n, 4, 4) and its consensus.

    Returns (the group's indices, the 4x4 consensus, its spread in degrees and metres).
    """
    R, t = implied[:, :3, :3], implied[:, :3, 3]
    near = ((_rotation_deg(R[:, None], R[None]) <= AGREE_DEG)
            & (np.linalg.norm(t[:, None] - t[None], axis=-1) <= AGREE_M))
    group = np.flatnonzero(near[np.argmax(near.sum(axis=1))])
    C = tdm.nearest_rigid(implied[group].mean(axis=0))  # chordal mean rotation, mean t
    return (group, C, float(_rotation_deg(R[group], C[:3, :3]).max()),
            float(np.linalg.norm(t[group] - C[:3, 3], axis=1).max()))


def _check_scene(scene: str, records: list[dict], poses: Mapping[int, np.ndarray],
                 exclude: set[int]) -> list[FragmentCheck]:
    """Check every fragment of one scene, leaving out the evidence of ``exclude``'s poses."""
    implied: dict[int, list[tuple[int, np.ndarray]]] = {}
    for r in records:
        i, j, T = int(r['target']), int(r['source']), np.asarray(r['transform'], dtype=float)
        if i not in exclude:
            implied.setdefault(j, []).append((i, poses[i] @ T))
        if j not in exclude:
            implied.setdefault(i, []).append((j, poses[j] @ np.linalg.inv(T)))
    checks = []
    for k, evidence in sorted(implied.items()):
        partners = np.array([p for p, _ in evidence])
        group, C, spread_deg, spread_m = consensus(np.stack([T for _, T in evidence]))
        size = len(set(partners[group]))
        offset_deg, offset_m = rotation_error_deg(poses[k], C), translation_error(poses[k], C)
        checks.append(FragmentCheck(
            scene, k, len(set(partners)), size, spread_deg, spread_m, offset_deg, offset_m, C,
            size >= MIN_PARTNERS and (offset_deg > DOUBT_DEG or offset_m > DOUBT_M)))
    return checks


def check_fragments(records: Iterable[Mapping], poses: Poses,
                    rounds: int = MAX_ROUNDS) -> dict[str, list[FragmentCheck]]:
    """
    Return every fragment's check, by scene, from the trusted (``valid``) estimates.

    ``poses``: ``{scene: {k: P_k}}`` (``p_world = P_k p_fragment``). Doubtful partners are
    left out of the evidence round after round until the doubtful set stops changing, in at
    most ``rounds`` rounds.
    """
    by_scene: dict[str, list[dict]] = {}
    for r in records:
        if r['valid']:
            by_scene.setdefault(r['scene'], []).append(r)
    out = {}
    for scene, trusted in sorted(by_scene.items()):
        doubtful: set[int] = set()
        for _ in range(rounds):
            checks = _check_scene(scene, trusted, poses[scene], doubtful)
            found = {c.fragment for c in checks if c.doubtful}
            if found == doubtful:
                break
            doubtful = found
        out[scene] = checks
    return out


def doubtful_fragments(records: Iterable[Mapping], poses: Poses | str | Path,
                       evidence: Iterable[Mapping] = ()) -> dict[str, list[FragmentCheck]]:
    """
    Return the doubtful fragments by scene (scenes without one left out).

    ``poses``: ``{scene: {k: P_k}}``, or the benchmark's root to read them from.
    ``evidence``: more records checked on their own (the settled truths of
    :mod:`bench.truth_settle`); a fragment either check doubts is doubtful, with the
    consensus of the check whose agreeing group is the larger.
    """
    records, evidence = list(records), list(evidence)
    if isinstance(poses, (str, Path)):
        poses = load_poses(poses, {r['scene'] for r in records + evidence})
    found = _doubtful(check_fragments(records, poses))
    for scene, checks in _doubtful(check_fragments(evidence, poses)).items():
        mine = {c.fragment: c for c in found.get(scene, ())}
        for c in (dataclasses.replace(c, evidence='settled') for c in checks):
            if c.fragment not in mine or c.group > mine[c.fragment].group:
                mine[c.fragment] = c
        found[scene] = sorted(mine.values(), key=lambda c: c.fragment)
    return found


def _doubtful(checks: Mapping[str, list[FragmentCheck]]) -> dict[str, list[FragmentCheck]]:
    return {s: d for s, cs in checks.items() if (d := [c for c in cs if c.doubtful])}


def in_doubt(record: Mapping, doubtful: Mapping[str, list[FragmentCheck]]) -> bool:
    """Return whether a record's pair holds a doubtful fragment (its truth is in doubt)."""
    pair = (int(record['target']), int(record['source']))
    return any(c.fragment in pair for c in doubtful.get(record['scene'], ()))


def corrected_truth(record: Mapping, poses: Poses,
                    doubtful: Mapping[str, list[FragmentCheck]]) -> np.ndarray:
    """Return ``inv(C_i) C_j`` of a record: consensus poses for doubtful fragments, else P."""
    C = {**poses[record['scene']],
         **{c.fragment: c.consensus for c in doubtful.get(record['scene'], ())}}
    return np.linalg.inv(C[int(record['target'])]) @ C[int(record['source'])]


def pairs_in_doubt(records: Iterable[Mapping], poses: Poses,
                   doubtful: Mapping[str, list[FragmentCheck]]) -> list[dict]:
    """Return each pair in doubt with its errors against the benchmark and the corrected truth."""
    out = []
    for r in filter(lambda r: in_doubt(r, doubtful), records):
        T, truth = np.asarray(r['transform']), corrected_truth(r, poses, doubtful)
        re, te = rotation_error_deg(T, truth), translation_error(T, truth)
        out.append({**dict(zip(('benchmark', 'scene', 'target', 'source'), pair_key(r))),
                    **{k: r[k] for k in ('valid', 'success', 're_deg', 'te_m')},
                    'corrected_re_deg': re, 'corrected_te_m': te,
                    'corrected_success': bool(re < MAX_RE_DEG and te < MAX_TE_M)})
    return out


def report(doubtful: Mapping[str, list[FragmentCheck]], pairs: list[dict]) -> str:
    """Return the Markdown table of doubtful fragments with their evidence and pairs."""
    headers = ['scene', 'fragment', 'evidence', 'partners', 'group', 'spread deg',
               'spread m', 'offset deg', 'offset m']
    for benchmark in tdm.BENCHMARKS:
        headers += [f'{benchmark} pairs', f'{benchmark} wrong, right if corrected']
    rows = []
    for scene, checks in doubtful.items():
        for c in checks:
            row = [scene, c.fragment, c.evidence, c.partners, c.group, c.spread_deg,
                   c.spread_m, c.offset_deg, c.offset_m]
            for benchmark in tdm.BENCHMARKS:
                held = [p for p in pairs if p['benchmark'] == benchmark and p['scene'] == scene
                        and c.fragment in (p['target'], p['source'])]
                row += [len(held), sum(not p['success'] and p['corrected_success']
                                       for p in held)]
            rows.append(row)
    return markdown_table(headers, rows, digits=3)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('records', type=Path, nargs='*',
                        default=[Path('out/loso_trust/records.jsonl')])
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--output', type=Path, default=Path('out/truth_check/doubtful'),
                        help='writes <output>.md and <output>.json')
    parser.add_argument('--evidence', type=Path, nargs='*', default=[],
                        help="records checked on their own as well (bench.truth_settle's)")
    args = parser.parse_args(argv)
    records, evidence = read_records(args.records), read_records(args.evidence)
    poses = load_poses(args.root, {r['scene'] for r in records + evidence})
    checks = [c for cs in check_fragments(records, poses).values() for c in cs]
    checks += [dataclasses.replace(c, evidence='settled')
               for cs in check_fragments(evidence, poses).values() for c in cs]
    doubtful = doubtful_fragments(records, poses, evidence)
    pairs = pairs_in_doubt(records, poses, doubtful)
    table = report(doubtful, pairs)
    counts = {b: sum(p['benchmark'] == b for p in pairs) for b in tdm.BENCHMARKS}
    checked = ', '.join(f'{n} by the {e}' for e in ('estimates', 'settled')
                        if (n := sum(c.evidence == e for c in checks)))
    summary = (f'{sum(map(len, doubtful.values()))} doubtful fragment(s), checked {checked}; '
               'pairs in doubt: ' + ', '.join(f'{b} {n}' for b, n in counts.items()))
    write_text(Path(f'{args.output}.md'), f'{table}\n\n{summary}\n')
    write_json(Path(f'{args.output}.json'), {
        'thresholds': {'agree_deg': AGREE_DEG, 'agree_m': AGREE_M, 'doubt_deg': DOUBT_DEG,
                       'doubt_m': DOUBT_M, 'min_partners': MIN_PARTNERS},
        'doubtful': {s: [c.as_dict() for c in cs] for s, cs in doubtful.items()},
        'pairs_in_doubt': pairs,
        'fragments': [{k: v for k, v in c.as_dict().items() if k != 'consensus'}
                      for c in checks]})
    print(f'{table}\n\n{summary}\nwrote {args.output}.md and {args.output}.json')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
