"""The wire in 3D: depth from the vessel prior in one view, triangulation from two (stage 5 of DESIGN.md).

One view (``single_view``: :func:`reconstruct_wire`, :class:`WireTracker`, the result :class:`Wire3D`),
in the order of its steps: ``context`` (per-pose tables, :class:`ReconOptions`), ``candidates`` (tree
points under the 2D wire), ``path`` (Viterbi through the tree), ``placement`` (each point on its ray,
inside the lumen), ``smoothing`` (the P-spline), ``uncertainty`` (per-point covariance); ``baselines``
(the paper's closed form, the B-spline). Two views: ``triangulation``.

The public names of the modules below, importable from ``guidewire3d.reconstruction``.
"""
from guidewire3d.reconstruction.baselines import (  # noqa: F401
    bspline_points,
    paper_depth_mm,
    paper_points,
)
from guidewire3d.reconstruction.candidates import (  # noqa: F401
    anchor_indices,
    tree_candidates,
)
from guidewire3d.reconstruction.context import (  # noqa: F401
    PIXEL_OPTIONS,
    REFERENCE_PIXEL_AT_ISO_MM,
    ReconOptions,
    ReconstructionContext,
    build_context,
    options_at_pixel,
    options_for_tree,
)
from guidewire3d.reconstruction.path import (  # noqa: F401
    LOST_MIN_SHIFT_MM,
    LOST_RAY_MM,
    LOST_RAY_STEP_FRACTION,
    LOST_REACH_MM,
    RIVAL_MIN_SHIFT_MM,
    TIP_SKIP_NEAR_PX,
    TOUCH_GEODESIC_MM,
    TOUCH_RADIUS_FRACTION,
    TRACK_UNSETTLED_EXTRA,
    TRACK_UNSETTLED_SHIFT_MM,
    TREE_END_LEAF_MM,
    TREE_END_MAX_PX,
    TREE_END_MIN_GAIN,
    PathCosts,
    ambiguity_mm2,
    branch_alternative,
    lost_lumen_stretch,
    path_retreat_mm,
    path_step_costs,
    route_excess_px,
    tip_rival,
    tip_skip_px,
    touching_rival,
    tracking_tip,
    tree_end_rival,
    viterbi_costs,
    viterbi_path,
)
from guidewire3d.reconstruction.placement import (  # noqa: F401
    ALONG_SCALE_MM,
    DIST_SCALE_MM,
    place_on_path,
)
from guidewire3d.reconstruction.single_view import (  # noqa: F401
    RETREAT_STEP_ANCHORS,
    Wire3D,
    WireTracker,
    reconstruct_wire,
)
from guidewire3d.reconstruction.smoothing import (  # noqa: F401
    arclength,
    curvature,
    fit_pspline,
    pspline_system,
    smooth_wire,
    tangents,
)
from guidewire3d.reconstruction.triangulation import (  # noqa: F401
    TwoViewContext,
    TwoViewOptions,
    TwoViewWire,
    extend_distal,
    fundamental_matrix,
    projection_error_px,
    triangulate_points,
    triangulate_wire,
)
from guidewire3d.reconstruction.uncertainty import (  # noqa: F401
    BEYOND_PATH_DEPTH_PER_MM,
    beyond_path_mm2,
    covariance_lumen,
    covariance_unconstrained,
    pose_jacobian,
)
