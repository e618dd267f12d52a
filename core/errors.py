"""Exception hierarchy. Every error a user can cause is a ``Guidewire3DError``.

The CLI prints ``str(err)`` on one line and exits with status 2.
"""


class Guidewire3DError(Exception):
    """Root of every error raised for bad input or an impossible request."""


class InputError(Guidewire3DError):
    """A file or argument is missing, unreadable or of the wrong kind."""


class DicomError(InputError):
    """A DICOM file is corrupt, incomplete or not of the expected modality."""


class OutputError(InputError):
    """The output folder cannot be written (a file in the way, no permission, a full disk), or
    another run is writing it."""


class GeometryError(Guidewire3DError):
    """An impossible C-arm geometry or pose."""


class SegmentationError(Guidewire3DError):
    """No usable structure was found (for example no vessels in a CTA)."""


class RegistrationError(Guidewire3DError):
    """Registration cannot be attempted, or a failed one is used without force."""


class ReconstructionError(Guidewire3DError):
    """Reconstruction cannot be attempted with the given inputs."""
