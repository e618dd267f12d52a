"""The wire in 3D: depth from the vessel prior in one view, triangulation from two (stage 5 of DESIGN.md).

The public names of the modules below, importable from ``guidewire3d.reconstruction``.
"""
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
from guidewire3d.reconstruction.wire import (  # noqa: F401
    ReconOptions,
    ReconstructionContext,
    Wire3D,
    WireTracker,
    build_context,
    paper_depth_mm,
    reconstruct_wire,
)
