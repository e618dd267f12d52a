"""The choices a user makes between methods, as Enums: the one place the command line, ``segment``,
the viewer and the Slicer module take their lists from.

Nothing heavy is imported here (the command line builds ``--help`` from it in milliseconds). The
implementations register themselves against these keys: :data:`guidewire3d.xray.segmentation.SEGMENTERS`
(one :class:`~guidewire3d.xray.segmentation.Segmenter` per :class:`SegMethod`) and
:func:`guidewire3d.reconstruction.reconstruct_wire` (one per :class:`ReconMethod`). A new
segmenter is a member here, one module implementing the interface, and its test.
"""
from __future__ import annotations

import enum

__all__ = ["SegMethod", "ReconMethod", "choices"]


class SegMethod(enum.Enum):
    """Guidewire segmentation method."""

    UNET = "unet"
    RIDGE = "ridge"


class ReconMethod(enum.Enum):
    """How depth is recovered (3D reconstruction method)."""

    VESSEL = "vessel"  #: vessel-tree Viterbi + ray/lumen intersection (default)
    PAPER = "paper"  #: the paper's closed-form depth, applied literally (degenerate in one view)
    BSPLINE = "bspline"  #: 2D B-spline lifted by the nearest centerline depth (no connectivity)


def choices(kind: type[enum.Enum]) -> tuple[str, ...]:
    """The values of an Enum of this module, in declaration order (argparse ``choices``)."""
    return tuple(m.value for m in kind)
