"""The simulator: vessel trees, CT, DRR roadmap and fluoroscopy frames with the true wire.

The public names of the modules below, importable from ``guidewire3d.phantom``.
"""
from guidewire3d.phantom.simulator import (  # noqa: F401
    BIPLANE_DEFAULT_SEPARATION_DEG,
    BREATHING_DEG_PER_MM,
    CACHE_VERSION,
    TREE_STEP_MM,
    WIRE_DIAMETERS_MM,
    WIRE_MARGIN_MM,
    WIRE_STEP_MM,
    PhantomCase,
    PhantomOptions,
    Truth,
    VolumeSize,
    add_cli_options,
    biplane_plane_b,
    cli_main,
    default_case_dir,
    default_options,
    load_truth,
    lumen_depth_mm,
    render_tube_line_integral,
    simulate,
    truth_dict,
    write_case,
)
