"""Registration of the 3D centerline tree to the 2D roadmap on SE(3) (stage 4 of DESIGN.md).

The modules, in the order a registration uses them:

* ``result``: :class:`RegistrationResult` and its :class:`Verdict`;
* ``model``: the inputs checked and sampled once (the 3D and 2D models);
* ``search``: the coarse global search that gives LM its starts;
* ``problem``: the robust bidirectional energy and its Levenberg-Marquardt;
* ``verdict``: residuals, score, covariance, jackknife and the verdict;
* ``solve``: the entry points :func:`register`, :func:`refine`, :func:`nudge`;
* ``epnp``: the EPnP baseline on matched landmarks.

Their public names are importable from ``guidewire3d.registration``. The named constants live in
the module that uses them and are read there at call time: patch them in that module (tests,
``scripts/bench_registration.py --set``), not here.
"""
from guidewire3d.registration.epnp import (  # noqa: F401
    match_bifurcations,
    register_epnp,
)
from guidewire3d.registration.model import (  # noqa: F401
    FIT_RMS_WEIGHT,
    RADIUS_GROWTH,
    SEARCH_CELL_PX,
    SIGMA_2D_PX,
    SIGMA_3D_MM,
)
from guidewire3d.registration.problem import (  # noqa: F401
    DELTA,
    DELTA_WIDE,
    EPS_ABS_MM,
    EPS_REL,
    GATE_NARROW_PX,
    GATE_WIDE_PX,
    LAMBDA,
    MU0,
    PATIENCE,
    REL_DECREASE_STOP,
    STABILISER,
    SUPPORT_GATE_PX,
    TANGENT_SLACK_PX,
    VISIBILITY_ROUNDS,
    pseudo_huber,
    two_stage_lm,
)
from guidewire3d.registration.result import (  # noqa: F401
    RegistrationResult,
    Verdict,
)
from guidewire3d.registration.search import (  # noqa: F401
    JOINT_WIDE_MINIMA,
    SEARCH_LARGE_TREE_RATIO,
    SEARCH_ROT_INPLANE_DEG,
    SEARCH_ROT_OUTPLANE_DEG,
    SEARCH_SHIFT_MAX_MM,
    SEARCH_SHIFT_MM,
    SEARCH_TRUNC_CELLS,
    SEARCH_WEIGHT_3D_LARGE_TREE,
    joint_wide_candidates,
    search_rotvecs,
    shift_range_mm,
)
from guidewire3d.registration.solve import (  # noqa: F401
    SEARCH_STARTS,
    nudge,
    refine,
    register,
)
from guidewire3d.registration.verdict import (  # noqa: F401
    COVARIANCE_INFLATION,
    COVARIANCE_SCREEN_FACTOR,
    DEPTH_PROFILE_FACTOR,
    DEPTH_PROFILE_ITERATIONS,
    DEPTH_SCAN_FAR_MM,
    DEPTH_SCAN_ITERATIONS,
    DEPTH_SCAN_OFFSETS_MM,
    DEPTH_SCAN_RISE,
    DEPTH_SCAN_SCREEN_FACTOR,
    DEPTH_SCAN_TOLERANCE,
    FULL_LIMIT_EXPLAINED_FRACTION,
    IN_VIEW_ONLY,
    INLIER_PX,
    JACKKNIFE_FACTOR,
    JACKKNIFE_ITERATIONS,
    JACKKNIFE_TILES,
    MAX_MEAN_RESIDUAL_PX,
    MAX_POSE_STD_MM,
    MAX_POSE_STD_MM_SINGLE_PATH,
    MIN_INLIER_FRACTION,
    MODEL_ERROR_GATE,
    MODEL_ERROR_LENGTH_PX,
    MODEL_ERROR_PX,
    SINGLE_PATH_FRACTION,
    pose_std_limit_mm,
    residuals_px,
    score,
)
