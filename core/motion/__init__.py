"""The pose followed frame by frame through breathing (``track_poses``, ``MotionTracker``).

The public names of the modules below, importable from ``guidewire3d.motion``.
"""
from guidewire3d.motion.tracking import (  # noqa: F401
    ACQUIRE_STARTS,
    ACROSS_ALONG_STEP_MM,
    ACROSS_RANGE_MM,
    ACROSS_STARTS,
    ACROSS_STEP_MM,
    BOTH_PLANES_MESSAGE,
    CROP_MARGIN_PX,
    MAX_CURVE_POINTS,
    MIN_CC_IN_PLANE,
    ONE_PLANE_MESSAGE,
    MOTION_PIXEL_OPTIONS,
    PLANES,
    SETTLE_CURVE_POINTS,
    SETTLE_ITERATIONS,
    SETTLE_STARTS,
    STEP_TOL_MM,
    STEP_TOL_RAD,
    BiplaneMotionTracker,
    MotionOptions,
    MotionTracker,
    curve_to_tree_distance_px,
    track_poses,
    track_poses_biplane,
    biplane_update_planes,
)
