"""guidewire3d: real-time 3D guidewire reconstruction from a CTA and single-view DSA."""
from guidewire3d.errors import (  # noqa: F401
    DicomError,
    GeometryError,
    Guidewire3DError,
    InputError,
    ReconstructionError,
    RegistrationError,
    SegmentationError,
)

__version__ = "0.1.0"
