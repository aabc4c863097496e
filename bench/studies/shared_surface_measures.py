r"""
Candidate measures of a pose's shared surface, computed from recorded transforms.

Run by hand on the records of :mod:`bench.no_overlap` (``cross``) and of
:mod:`bench.studies.loso_trust` (``measure``: the benchmark's pairs), without registering
again::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.studies.shared_surface_measures \
        out/no_overlap/cross.jsonl out/loso_trust/records.jsonl \
        --output out/no_overlap/measures.jsonl [--only-valid]
    OMP_NUM_THREADS=1 .venv/bin/python -m bench.studies.shared_surface_measures \
        --free-space out/no_overlap/measures.jsonl --output out/no_overlap/measures_fs.jsonl
    .venv/bin/python -m bench.studies.shared_surface_measures --separate \
        out/no_overlap/measures.jsonl

For each recorded estimate (its transform, source -> target) it measures what a gate that
tells clouds of two places from right poses of low overlap could read: the overlap's
extent in each cloud and the coarse cells it covers, where the correspondences' inliers
lie over it (their share of the overlap's cells, their extent against the overlap's), the
free space seen from each sensor and from both at other margins and angular bins
(``--free-space``, a separate pass that needs no features), the descriptors'
agreement over the overlap at three FPFH radii, the share of the overlap's mutual nearest
descriptor matches that the pose puts together, and the overlap's normals.
``--separate`` prints, per measure, the accepted cross pairs' values against the
distribution over the right valid 3DLoMatch poses (the quantile each lies at).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from bench.common import argument_parser
from bench.datasets import threedmatch as tdm
from bench.no_overlap import read_records
from cgags_ros.config import PipelineConfig
from cgags_ros.frontend.features import downsample, extract_features, MIN_POINTS
from cgags_ros.frontend.fpfh import FPFH_MAX_NN, fpfh_with_spacing
from cgags_ros.frontend.keypoints import match_keypoints
from cgags_ros.frontend.refine import evaluate_alignment
from cgags_ros.geometry import apply_transform
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline.free_space import free_space_violation
from cgags_ros.pipeline.gates import observability
import numpy as np
from scipy.spatial import cKDTree

SCALES = (2.0, 4.0)  # FPFH radii beyond the front end's, as multiples of its own
MARGINS = (0.5, 1.0, 2.0)  # free space: depth margins, voxels
BINS = (2.0, 3.0, 4.0)  # and angular bins, degrees


def normalised(rec: dict) -> dict:
    """Return a record of either study in one form (kind, scenes, fragments, verdict)."""
    if 'benchmark' in rec:
        rec = {**rec, 'kind': rec['benchmark'], 'source_scene': rec['scene'],
               'target_scene': rec['scene']}
    keep = ('kind', 'source_scene', 'source', 'target_scene', 'target', 'valid', 'success',
            'refusal', 'confidence', 'transform', 'inlier_threshold', 'gt_overlap',
            'free_space_violation', 'observability', 'fitness', 'overlap')
    out = {k: rec.get(k) for k in keep}
    out['code'] = (rec.get('refusal') or '').split(':')[0] or None
    return out


class Clouds:
    """Every fragment's features at 5 cm (and its FPFH at larger radii), computed once."""

    def __init__(self, root: Path, cfg: PipelineConfig):
        self.root, self.cfg = root, cfg
        self.frags: dict[str, tdm.Fragments] = {}
        self.features: dict = {}

    def get(self, scene: str, k: int):
        """Return fragment ``k`` of ``scene``: its features and its wider descriptors."""
        key = (scene, k)
        if key not in self.features:
            frags = self.frags.setdefault(scene, tdm.Fragments(self.root, scene))
            f = extract_features(frags[k], self.cfg.voxel_size, self.cfg.frontend)
            wider = []
            radius = self.cfg.frontend.fpfh_radius_factor
            for s in SCALES:  # as many neighbours as the wider ball holds, not the first 100
                fe = dataclasses.replace(self.cfg.frontend, fpfh_radius_factor=s * radius)
                wider.append(fpfh_with_spacing(f.points, f.normals, self.cfg.voxel_size, fe,
                                               max_nn=int(FPFH_MAX_NN * s * s))[0])
            self.features[key] = (f, wider)
        return self.features[key]


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def _desc_ratio(ds: np.ndarray, dt: np.ndarray) -> float:
    ds, dt = _unit(ds), _unit(dt)
    paired = np.median(np.linalg.norm(ds - dt, axis=1))
    chance = np.median(np.linalg.norm(ds - dt[np.random.default_rng(0).permutation(len(dt))],
                                      axis=1))
    return float(paired / chance) if chance > 0 else float('nan')


def _spread(points: np.ndarray) -> list[float]:
    if len(points) < 3:
        return [0.0, 0.0, 0.0]
    c = points - points.mean(axis=0)
    return np.sqrt(np.maximum(np.linalg.eigvalsh(c.T @ c / len(c))[::-1], 0)).tolist()


def _cells(points: np.ndarray, size: float) -> set:
    return set(map(tuple, np.floor(points / size).astype(np.int64)))


def _mutual_share(ds: np.ndarray, dt: np.ndarray, ps: np.ndarray, pt: np.ndarray,
                  radius: float) -> tuple[float, float]:
    """
    Return the share of the mutual nearest descriptor matches within ``radius`` under the pose.

    ``ds``/``dt`` the descriptors of the overlap's source and target points, ``ps``/``pt``
    their positions (the source moved by the pose); and the share a random pairing puts
    that close (the chance level of the first).
    """
    ds, dt = _unit(ds), _unit(dt)
    fwd = cKDTree(dt).query(ds)[1]
    back = cKDTree(ds).query(dt)[1]
    mutual = np.flatnonzero(back[fwd] == np.arange(len(ds)))
    if len(mutual) == 0:
        return 0.0, 0.0
    close = np.linalg.norm(ps[mutual] - pt[fwd[mutual]], axis=1) <= radius
    near = cKDTree(pt).query_ball_point(ps, r=radius, return_length=True)
    return float(close.mean()), float(np.mean(near) / len(pt))


def measures(cl: Clouds, rec: dict) -> dict:
    """Return the candidate measures of ``rec``'s transform (empty without an estimate)."""
    cfg, v = cl.cfg, cl.cfg.voxel_size
    fs, ws = cl.get(rec['source_scene'], rec['source'])
    ft, wt = cl.get(rec['target_scene'], rec['target'])
    T = np.asarray(rec['transform'], dtype=np.float64)
    d = cfg.refine.max_correspondence_distance_factor * v
    a = evaluate_alignment(fs.points, ft.tree, T, d)
    b = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(T), d)
    if len(a.source_index) < 10 or len(b.source_index) < 10:
        return {'shared_points': int(min(len(a.source_index), len(b.source_index)))}
    out: dict = {'shared_points': int(min(len(a.source_index), len(b.source_index)))}
    src_ov = apply_transform(T, fs.points[a.source_index])  # in the target frame
    tgt_ov = ft.points[b.source_index]
    out['extent_source'] = _spread(src_ov)
    out['extent_target'] = _spread(tgt_ov)
    out['extent_min2'] = min(out['extent_source'][1], out['extent_target'][1])
    out['extent_min1'] = min(out['extent_source'][0], out['extent_target'][0])
    for size in (0.25, 0.5):
        out[f'cells_{size:g}'] = min(len(_cells(src_ov, size)), len(_cells(tgt_ov, size)))
    # descriptors over the overlap, at the front end's radius and wider
    ds_all = [fs.descriptors, *ws]
    dt_all = [ft.descriptors, *wt]
    for name, dsx, dtx in zip(('1', *(f'{s:g}' for s in SCALES)), ds_all, dt_all):
        out[f'desc_ratio_{name}'] = _desc_ratio(dsx[a.source_index], dtx[a.target_index])
        out[f'desc_ratio_back_{name}'] = _desc_ratio(dtx[b.source_index], dsx[b.target_index])
    for name, dsx, dtx in zip(('1', '4'), (fs.descriptors, ws[1]), (ft.descriptors, wt[1])):
        share, chance = _mutual_share(dsx[a.source_index], dtx[b.source_index], src_ov, tgt_ov,
                                      3 * v)
        out[f'mutual_share_{name}'] = share
        out[f'mutual_chance_{name}'] = chance
    # normals: their agreement over the pairs, and how many directions the overlap faces
    ns = fs.normals[a.source_index] @ T[:3, :3].T
    nt = ft.normals[a.target_index]
    out['normal_angle_deg'] = float(np.degrees(np.median(np.arccos(np.clip(
        np.abs(np.sum(ns * nt, axis=1)), 0, 1)))))
    scatter = np.linalg.eigvalsh(nt.T @ nt / len(nt))
    out['normal_spread'] = float(scatter[0])
    out['normal_spread_mid'] = float(scatter[1])
    out['observability'] = observability(fs.points, ft.normals, a)
    # the correspondences' inliers under the pose, and how they spread over the overlap
    corr = match_keypoints(fs.points, fs.descriptors, ft.descriptors, v, cfg.frontend)
    tau = rec.get('inlier_threshold') or 3 * v
    ps = apply_transform(T, fs.points[corr.source_index])
    pt = ft.points[corr.target_index]
    inl = np.linalg.norm(ps - pt, axis=1) <= tau
    in_ov = np.isin(corr.source_index, a.source_index)
    out['corr_inliers'] = int(inl.sum())
    out['corr_in_overlap'] = int(in_ov.sum())
    out['overlap_inlier_ratio'] = float(inl[in_ov].mean()) if in_ov.any() else 0.0
    tight = np.linalg.norm(ps - pt, axis=1) <= 2 * v
    out['overlap_tight_ratio'] = float(tight[in_ov].mean()) if in_ov.any() else 0.0
    ip = ps[inl & in_ov]
    for size in (0.25, 0.5):
        cov = _cells(src_ov, size)
        out[f'inlier_cells_share_{size:g}'] = (len(_cells(ip, size) & cov) / len(cov)
                                               if len(ip) else 0.0)
    ie = _spread(ip)
    out['inlier_extent'] = ie
    out['inlier_extent_ratio2'] = ie[1] / max(out['extent_source'][1], 1e-9)
    return out


def free_space_grid(source: np.ndarray, target: np.ndarray, T: np.ndarray, v: float) -> dict:
    """
    Return the free-space violation seen from each sensor, and from both, at other settings.

    ``fs_s_M_B``: the target's points seen from the source's sensor, ``fs_t_M_B`` the
    source's seen from the target's (margin M voxels, angular bin B degrees); ``fs_min_M_B``
    the smaller of the two (surfaces put in free space as both sensors see it) and
    ``fs_max_M_B`` the larger (what the gate reads, at its own margin and bin).
    """
    out = {}
    for margin in MARGINS:
        for bin_deg in BINS:
            key = f'{margin:g}_{bin_deg:g}'
            s = free_space_violation(source, target, T, margin * v, bin_deg, False, True)
            t = free_space_violation(source, target, T, margin * v, bin_deg, True, False)
            out.update({f'fs_s_{key}': s, f'fs_t_{key}': t, f'fs_min_{key}': min(s, t),
                        f'fs_max_{key}': max(s, t)})
    return out


def add_free_space(paths: list[Path], output: Path, root: Path) -> None:
    """Write ``paths``' records with :func:`free_space_grid` of each measured estimate."""
    v = 0.05
    frags: dict[str, tdm.Fragments] = {}
    points: dict = {}

    def cloud(scene: str, k: int) -> np.ndarray:
        if (scene, k) not in points:
            f = frags.setdefault(scene, tdm.Fragments(root, scene))
            points[(scene, k)] = downsample(np.asarray(f[k], dtype=np.float64), v, MIN_POINTS)
        return points[(scene, k)]

    output.parent.mkdir(parents=True, exist_ok=True)
    with open(output, 'w', encoding='utf-8') as sink:
        for r in read_records(paths):
            if 'desc_ratio_1' in r:
                r.update(free_space_grid(cloud(r['source_scene'], r['source']),
                                         cloud(r['target_scene'], r['target']),
                                         np.asarray(r['transform']), v))
            sink.write(json.dumps(r) + '\n')


def run(paths: list[Path], output: Path, root: Path, only_valid: bool) -> None:
    cfg = PipelineConfig(voxel_size=0.05)
    cl = Clouds(root, cfg)
    recs = [normalised(r) for r in read_records(paths)]
    recs.sort(key=lambda r: (r['source_scene'], r['target_scene']))
    output.parent.mkdir(parents=True, exist_ok=True)
    with open(output, 'w', encoding='utf-8') as sink:
        for i, r in enumerate(recs):
            measured = (r['transform'] is not None and (r['fitness'] or 0) > 0
                        and (r['valid'] or not only_valid))
            sink.write(json.dumps({**r, **(measures(cl, r) if measured else {})}) + '\n')
            if (i + 1) % 100 == 0:
                print(f'{i + 1}/{len(recs)}', flush=True)


def _flat(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if isinstance(v, (int, float)) and not
            isinstance(v, bool)}


def separate(path: Path) -> None:
    """Print each measure's accepted cross values against the right valid 3DLoMatch poses'."""
    recs = read_records([path])
    right = [r for r in recs if r['kind'] == '3DLoMatch' and r['valid'] and r['success']]
    cross = [r for r in recs if r['kind'] == 'cross' and r['valid']]
    names = sorted({k for r in right for k in _flat(r)})
    for name in names:
        xs = np.array([r.get(name) for r in right if r.get(name) is not None], dtype=float)
        xs = xs[np.isfinite(xs)]
        if not len(xs):
            continue
        cells = []
        for c in cross:
            x = c.get(name)
            if x is None:
                continue
            below = np.mean(xs < x)
            cells.append(f'{x:.3g} (q {below:.3f})')
        q = np.quantile(xs, [0, 0.01, 0.02, 0.5, 0.98, 0.99, 1])
        print(f'{name}: right LoMatch {len(xs)} q0/1/2/50/98/99/100 '
              + ' '.join(f'{v:.3g}' for v in q) + ' | cross: ' + ', '.join(cells))


def main(argv: list[str] | None = None) -> None:
    parser = argument_parser('bench.studies.shared_surface_measures', __doc__)
    parser.add_argument('records', nargs='+', type=Path)
    parser.add_argument('--output', type=Path, default=Path('out/no_overlap/measures.jsonl'))
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--only-valid', action='store_true',
                        help='measure the valid estimates only (the others are copied)')
    parser.add_argument('--separate', action='store_true')
    parser.add_argument('--free-space', action='store_true',
                        help='add the free-space grid to measured records (fast: no features)')
    args = parser.parse_args(argv)
    if args.separate:
        separate(args.records[0])
    elif args.free_space:
        add_free_space(args.records, args.output, args.root)
    else:
        run(args.records, args.output, args.root, args.only_valid)


if __name__ == '__main__':
    main()
