"""The simulator: vessel trees, CT, DRR roadmap and fluoroscopy frames with the true wire.

Everything is procedural and reproducible from one integer seed. One call to :func:`simulate`
builds a :class:`PhantomCase`; :func:`write_case` writes it as DICOM (CT series, XA roadmap,
XA live frames, XA held-out view) plus ``truth.json`` and ``truth_masks.npz``;
:func:`load_truth` reads the truth back. The model, stage by stage:

* ``anatomy``: the CT grid, a random tortuous vessel tree, its lumen (union of tapered tubes) and the
  guidewire's path inside it;
* ``ct``: the CTA on that grid (contrast lumen with partial volume, soft tissue, optional bone and
  contrast blobs, blur, noise);
* ``xray``: the true patient pose, the C-arm views (and biplane plane B), and the X-ray images: the
  DRR roadmap of the lumen and the live fluoroscopy frames of the wire and catheter;
* ``motion``: the patient's motion per frame (a rigid shift, breathing, a cardiac contraction);
* ``case``: :class:`PhantomOptions`, :func:`simulate` (the stages above, each from its own random
  stream) and :class:`PhantomCase`;
* ``files``: the written case and its :class:`Truth`, the cached default case, and the
  ``guidewire3d phantom`` command;
* ``realct``: a case on a real CT and its structure labels (``guidewire3d phantom --anatomy-ct``).

The public names of the modules below, importable from ``guidewire3d.phantom``.
"""
from guidewire3d.phantom.anatomy import (  # noqa: F401
    TREE_STEP_MM,
    WIRE_DIAMETERS_MM,
    WIRE_MARGIN_MM,
    WIRE_STEP_MM,
    VolumeSize,
    lumen_depth_mm,
)
from guidewire3d.phantom.case import PhantomCase, PhantomOptions, simulate  # noqa: F401
from guidewire3d.phantom.files import (  # noqa: F401
    CACHE_VERSION,
    Truth,
    add_cli_options,
    cli_main,
    default_case_dir,
    default_options,
    load_truth,
    truth_dict,
    write_case,
)
from guidewire3d.phantom.motion import BREATHING_DEG_PER_MM  # noqa: F401
from guidewire3d.phantom.realct import (  # noqa: F401
    ARTERY_NAME,
    BLOOD_HU,
    CONTRAST_NAME,
    TIP_STEP_MM,
    VIEW_MM,
    RealAnatomyOptions,
    anatomy_mu_zyx,
    iodine_fraction_zyx,
    ray_integral,
    read_labels,
    simulate_real_anatomy,
    true_wire_lps_mm,
)
from guidewire3d.phantom.xray import (  # noqa: F401
    BIPLANE_DEFAULT_SEPARATION_DEG,
    biplane_plane_b,
    render_tube_line_integral,
)
