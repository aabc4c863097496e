"""
One-off studies behind the shipped defaults: the lab notebook, not tools.

Each runs as ``python -m bench.studies.<name>`` from the repository root and writes under
the git-ignored ``out/``. No test imports them (test/test_bench.py checks that), nor does
any other bench module: they may import the tools of :mod:`bench`, never the reverse.

- :mod:`.fit`: the one entry that regenerates the constants these studies fit (the
  confidence's weights, the twins' limits, the covariance's scale, floors and
  doubt) from their measurement records, printed as the source holds them.
- :mod:`.loso_trust`: measures every 3DMatch pair once (the gates' values, the covariance's
  inputs, the twins, the error against the truth): the records the trust
  studies fit on.
- :mod:`.loso_trust_study`: over those records, each lever chosen on three scenes and
  reported on the fourth; fits the covariance's scale and floors and the doubt that opens
  it (``cgags_ros/pipeline/covariance.py``).
- :mod:`.trust_shift`: the valid flag chosen on easier scenes and reported on harder ones;
  fits the confidence's weights (``cgags_ros/pipeline/confidence.py``) and the twins'
  limits (``cgags_ros/pipeline/twins.py``, ``cgags_ros/validity/__init__.py``).
- :mod:`.trust_limits`: where the valid flag's held-out misses come from: the wrong poses
  it lets through, stricter operating points, and the right poses refused as ambiguous.
- :mod:`.gate_study`: replays extra gates over ``bench.threedmatch`` records, without
  registering again.
- :mod:`.chance_sample`: what stage one's minimal subsets explain by chance (the chance
  level's estimate), per motion model and outlier layout.
- :mod:`.gt_consistency`: how far a pair's ground truth lies from the best alignment its
  own geometry supports.
- :mod:`.ablation_core`: the core's options still open, each variant on the same problems.
- :mod:`.regenerate`: the regenerated correspondences' right matches, and which way of
  choosing among the poses they propose is right (``cgags_ros/pipeline/regenerate.py``).
- :mod:`.certain_refusals`: the refusals decided before the refinement, refined and gated
  anyway: what skipping that work gives up.
- :mod:`.core_stall`: when the core's best consensus is found, and what a cap or a stop on
  a stalled search would cut (replayed on every pair's recorded improvements).
- :mod:`.revoted_translations`: a refused estimate's translation voted again under its
  rotation (a slide's right translation): how often one is right, and which rule finds it.
- :mod:`.recall_time`: recall against median time of settings run side by side with
  KISS-Matcher (``bench.threedmatch --variant``), and settings chosen on the easiest scenes,
  reported on the hardest.
- :mod:`.no_overlap_bound`: the shared-surface gate's bounds (``gates.min_shared_area``,
  ``gates.max_descriptor_ratio``) chosen on the right low-overlap poses of the training
  scenes, leave one scene out and easiest to hardest (docs/no_overlap.md).
- :mod:`.shared_surface_measures`: candidate measures of a pose's shared surface (extent,
  inliers' spread, descriptors at three radii, mutual descriptor matches, free space from
  each sensor and both) from recorded transforms, against the right low-overlap poses.
- :mod:`.place_ranking`: the share of chance votes a place's score discounts
  (``cgags_ros/pipeline/places.py``), on the maps of ``bench.maps``.
- :mod:`.submap_index`: a place's submap index cut from the map's cells or fitted to it,
  and the cells' size (``SUBMAP_SHARE``, ``cgags_ros/pipeline/places.py``).
- :mod:`.room_alone`: each query of ``bench.maps``' four-room floor against the floor and
  against its own room alone: what the places lose beyond the front end's limit.
"""
