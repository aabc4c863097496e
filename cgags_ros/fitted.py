"""
The numbers a study fitted, beside the record they are checked against.

Every number here was chosen by the trust study on real RGB-D pairs (the four shared 3DMatch
scenes, both lists; docs/confidence.md, docs/ablation.md), not by hand:

- the confidence (:mod:`cgags_ros.pipeline.confidence`): a logistic model's weights and
  intercept, and the gates' ``min_confidence`` default;
- the twins (:mod:`cgags_ros.pipeline.twins`, :mod:`cgags_ros.validity`): which twins are
  settled, and when a settled twin makes an estimate ambiguous;
- the covariance (:mod:`cgags_ros.pipeline.covariance`): the overlap's scale and floors, how
  it opens with the doubt the confidence leaves, and the gates' ``max_position_sigma``
  default;
- the most a refused estimate's confidence may say (:mod:`cgags_ros.pipeline.confidence`):
  the share of right estimates among the gates' refusals of each kind.

Study: :mod:`bench.studies.trust_shift` (confidence, twins, the two defaults),
:mod:`bench.studies.loso_trust_study` (covariance) and :mod:`bench.no_overlap` (the
refusals, with the defaults). Command: ``python -m bench.studies.fit`` prints what the
records give, as this module writes it. Records: ``bench/studies/records/trust.jsonl.gz``
and ``refusals.jsonl.gz`` (their README says how they were measured, and their licence:
3DMatch's, research and non-commercial). ``test/test_fitted.py`` re-fits from the records
and fails when a number here is not what its record gives.
"""


# The confidence's logistic model on its raw inputs (:data:`.pipeline.confidence.FEATURES`).
CONFIDENCE_WEIGHTS = {'log_margin': 1.154, 'log_sigma': -3.719, 'free_space': -17.43}
CONFIDENCE_INTERCEPT = 5.015
MIN_CONFIDENCE = 0.5  # the default of gates.min_confidence

# A twin is settled when its start fits this share of the estimate's fitness ...
TWIN_PROMISING = 0.5
# ... and makes the estimate ambiguous when it settles this many voxels from it, fits about
# as well (within this ratio) and stacks no more than this share in free space.
TWIN_APART = 3.0
TWIN_OVERLAP_RATIO = 2.0
TWIN_MAX_VIOLATION = 0.05

# The overlap covariance: cells of this many voxels, this scale, floors in voxels.
COVARIANCE_CELL_FACTOR = 4
COVARIANCE_SCALE = 12.7
COVARIANCE_FLOOR_POSITION = 0.5
COVARIANCE_FLOOR_ROTATION = 0.5
# A wrong estimate's error spread (voxel sizes a position axis, radians a rotation axis), and
# how fast the chance of a wrong pose falls with the confidence.
WRONG_POSITION_VOXELS = 63.59
WRONG_ROTATION = 1.414
DOUBT_EXPONENT = 1.5
MAX_POSITION_SIGMA = 19.78  # voxels: the default of gates.max_position_sigma

# The share of right estimates among the gates' refusals of each kind with enough of them
# (refusal code: share), and among all the gates' refusals (for the other kinds): a refused
# estimate's confidence says no more, since the model rates the pose, not the refusal.
REFUSED_RIGHT = {'ambiguous': 0.59, 'no_shared_surface': 0.096, 'free_space': 0.28,
                 'degenerate_axis': 0.33, 'chance_level': 0.36}
REFUSED_RIGHT_OTHER = 0.34
