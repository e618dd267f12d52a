"""The per-frame engine: one ``Session`` segments, orders, reconstructs and judges each live frame.

The public names of the modules below, importable from ``guidewire3d.live``.
"""
from guidewire3d.live.continuation import (  # noqa: F401
    BACKGROUND_PX,
    BEYOND_MM,
    MIN_CONTRAST_RATIO,
    MIN_SAMPLES,
    MIN_Z,
    NEAR_WIRE_PX,
    OFFSET_PX,
    SKIP_PX,
    WINDOW_PX,
    WireContinuation,
    downstream_paths,
    wire_continuation,
)
from guidewire3d.live.tipslide import SLIDE_CLEARANCE_MM, SLIDE_MAX_MM, tip_slide_mm  # noqa: F401
from guidewire3d.live.session import (  # noqa: F401
    BRANCH_EXTRA_MAX,
    BRANCH_SHIFT_MIN_MM,
    HINT_MARGIN_ALONE,
    HINT_MARGIN_MIN,
    LOOK_AGAIN_PX,
    LOST_LUMEN_STRETCH_MAX_MM,
    LOST_LUMEN_WORDS,
    OFF_LUMEN_MAX_MM,
    TIP_BORDER_PX,
    TIP_MAX_UNCERTAINTY_MM,
    TIP_SKIP_MAX_PX,
    TIP_STRETCH_MAX_MM,
    TIP_STRETCH_PX,
    TRACKED_SHRINK_FRACTION,
    TRACKED_SHRINK_MIN_PX,
    TREE_RETREAT_MAX_MM,
    TREE_RISE_MIN_MM,
    WIRE_MAX_UNCERTAINTY_MM,
    FrameResult,
    Orientation,
    Session,
    frame_verdict,
    log,
    orientation_of,
    tip_stretch_mm,
    wire_uncertainty_mm,
)
