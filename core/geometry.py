"""C-arm projection geometry and SE(3) poses.

The convention is the normative one of DESIGN.md ("C-arm geometry"). In short:

* World frame: DICOM patient LPS, millimetres (the CTA's frame).
* ``Pose`` ``T_iso_from_lps`` maps CTA LPS points into the C-arm *room* frame: axes parallel to
  LPS, origin at the isocentre. At the nominal pose the isocentre sits at the vessel-tree
  centroid, i.e. ``Pose(R=I, t=-centroid)``. Registration estimates this pose.
* In the room frame, with primary angle alpha (LAO +) and secondary angle beta (CRA +)::

      d   = ( sin a cos b, -cos a cos b,  sin b)     beam, source -> detector
      e_u = ( cos a,        sin a,        0    )     image columns (u grows)
      e_v = ( sin b sin a, -sin b cos a, -cos b)     image rows (v grows)
      S   = -SOD d,   D = (SID - SOD) d
      P   = K [R | -R S],  R = rows(e_u, e_v, d),  K = [[SID/ps, 0, cu], [0, SID/ps, cv], [0, 0, 1]]

  ``det R = -1``: the radiological display is a mirror of a camera frame. It is kept as is.
* Pixel ``(u, v) = (col, row)``; ``(0, 0)`` is the centre of the first pixel; the principal
  point is the image centre ``((cols - 1) / 2, (rows - 1) / 2)``.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np
from guidewire3d.errors import GeometryError

__all__ = ["Pose", "CArm", "hat", "so3_exp", "so3_log", "REFERENCE_PIXEL_AT_ISO_MM", "fine_pixel_factor",
           "options_in_mm"]

#: the pixel size at the isocentre (mm) the lengths in pixels of the reconstruction, the frame verdict and
#: the motion tracker were tuned at: the simulator's 512 px views (0.10-0.25 mm, median about 0.17). On a
#: finer detector the same error in mm spans more pixels: a 1024 px panel (0.09-0.12 mm) doubled the path
#: costs (``reconstruction.context.options_at_pixel``, stop 32). Below this size such lengths are widened
#: to their size in mm here (``fine_pixel_factor``); at this size or coarser they are used as they are
REFERENCE_PIXEL_AT_ISO_MM = 0.16


def fine_pixel_factor(pixel_at_iso_mm: float) -> float:
    """``REFERENCE_PIXEL_AT_ISO_MM / pixel_at_iso_mm`` when that is above 1 (a detector finer than the
    reference), else exactly 1.0: a length of ``L`` px tuned at the reference holds its size in mm as
    ``L * fine_pixel_factor(px)`` px on a finer view, and is left as it is on a coarser one.

    Parameters
    ----------
    pixel_at_iso_mm : float
        The view's pixel at the isocentre (``CArm.pixel_at_iso_mm``), mm; positive and finite.
    """
    px = float(pixel_at_iso_mm)
    if not (np.isfinite(px) and px > 0):
        raise GeometryError(f"pixel at the isocentre must be a positive number of mm, got {pixel_at_iso_mm!r}")
    k = REFERENCE_PIXEL_AT_ISO_MM / px
    return k if k > 1.0 else 1.0


@functools.lru_cache(maxsize=64)
def options_in_mm(options, names: tuple[str, ...], pixel_at_iso_mm: float):
    """A frozen options dataclass with its lengths in pixels (the fields ``names``) multiplied by
    ``fine_pixel_factor(pixel_at_iso_mm)`` on a finer view; on a view at the reference or coarser,
    ``options`` itself (the same object). Cached: every frame of a view asks for the same options."""
    k = fine_pixel_factor(pixel_at_iso_mm)
    if k == 1.0:
        return options
    return dataclasses.replace(options, **{n: getattr(options, n) * k for n in names})

_EPS = 1e-12


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.setflags(write=False)
    return a


def hat(w) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector: ``hat(w) @ x == cross(w, x)``."""
    w = np.asarray(w, dtype=float)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(phi) -> np.ndarray:
    """Rodrigues' formula: rotation vector (rad) -> rotation matrix."""
    phi = np.asarray(phi, dtype=float)
    theta = float(np.linalg.norm(phi))
    K = hat(phi)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1.0 - np.cos(theta)) / theta**2 * K @ K


def so3_log(R) -> np.ndarray:
    """Rotation matrix -> rotation vector (rad), valid on the whole of SO(3)."""
    R = np.asarray(R, dtype=float)
    cos_t = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    if theta < 1e-8:
        return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.pi - theta < 1e-6:
        # near pi: axis from the largest diagonal element of (R + I) / 2
        B = (R + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / np.sqrt(max(B[i, i], _EPS))
        return axis / np.linalg.norm(axis) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return theta / (2.0 * np.sin(theta)) * w


def _so3_left_jacobian(phi) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    K = hat(phi)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1.0 - np.cos(theta)) / theta**2 * K
        + (theta - np.sin(theta)) / theta**3 * K @ K
    )


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid transform in SE(3): ``x' = R @ x + t`` (mm).

    Tangent vectors ``xi`` are ``(tx, ty, tz, rx, ry, rz)``: translation part first (mm),
    rotation vector second (rad), as in ``exp(xi) = [[exp(hat(r)), V t], [0, 1]]``.
    """

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        R = np.asarray(self.R, dtype=float)
        t = np.asarray(self.t, dtype=float).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise GeometryError(f"Pose needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        if not np.all(np.isfinite(R)) or not np.all(np.isfinite(t)):
            raise GeometryError("Pose has non-finite entries")
        if abs(np.linalg.det(R) - 1.0) > 1e-6 or np.abs(R @ R.T - np.eye(3)).max() > 1e-6:
            raise GeometryError("Pose.R is not a rotation matrix (det must be +1, R R^T = I)")
        object.__setattr__(self, "R", _readonly(R))
        object.__setattr__(self, "t", _readonly(t))

    # --- construction -------------------------------------------------------------------
    @classmethod
    def identity(cls) -> "Pose":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T) -> "Pose":
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9:
            raise GeometryError(f"expected a 4x4 homogeneous rigid matrix, got shape {T.shape}")
        return cls(T[:3, :3], T[:3, 3])

    @classmethod
    def exp(cls, xi) -> "Pose":
        xi = np.asarray(xi, dtype=float).reshape(6)
        rho, phi = xi[:3], xi[3:]
        return cls(so3_exp(phi), _so3_left_jacobian(phi) @ rho)

    @classmethod
    def from_rotvec_about(cls, rotvec_rad, centre_mm) -> "Pose":
        """Rotation by ``rotvec_rad`` about the point ``centre_mm``."""
        R = so3_exp(rotvec_rad)
        c = np.asarray(centre_mm, dtype=float)
        return cls(R, c - R @ c)

    # --- algebra ------------------------------------------------------------------------
    def log(self) -> np.ndarray:
        phi = so3_log(self.R)
        rho = np.linalg.solve(_so3_left_jacobian(phi), self.t)
        return np.concatenate([rho, phi])

    def inverse(self) -> "Pose":
        return Pose(self.R.T, -self.R.T @ self.t)

    def __matmul__(self, other: "Pose") -> "Pose":
        if not isinstance(other, Pose):
            return NotImplemented
        return Pose(self.R @ other.R, self.R @ other.t + self.t)

    def apply(self, points_mm) -> np.ndarray:
        """Transform ``(N, 3)`` (or ``(3,)``) points; returns a new array."""
        p = np.asarray(points_mm, dtype=float)
        return p @ self.R.T + self.t

    @property
    def matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def rotation_angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(so3_log(self.R))))

    def allclose(self, other: "Pose", *, atol_mm: float = 1e-6, atol_rad: float = 1e-9) -> bool:
        d = self.inverse() @ other
        return bool(np.linalg.norm(d.t) <= atol_mm and np.linalg.norm(so3_log(d.R)) <= atol_rad)

    def to_dict(self) -> dict:
        return {"matrix": self.matrix.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Pose":
        return cls.from_matrix(np.asarray(d["matrix"], dtype=float))

    def __repr__(self) -> str:
        return f"Pose(rot={self.rotation_angle_deg():.3f} deg, t={np.round(self.t, 3).tolist()} mm)"


@dataclass(frozen=True, eq=False)
class CArm:
    """C-arm view from XA positioner tags (see DESIGN.md, 'C-arm geometry')."""

    primary_deg: float  # LAO +  (0018,1510)
    secondary_deg: float  # CRA +  (0018,1511)
    sid_mm: float  # source to detector (0018,1110)
    sod_mm: float  # source to isocentre (0018,1111)
    pixel_mm: float  # at the detector (0018,1164)
    shape: tuple[int, int]  # (rows, cols)

    def __post_init__(self):
        for name in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm", "pixel_mm"):
            v = getattr(self, name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise GeometryError(f"CArm.{name} must be a number, got {v!r}") from None
            if not np.isfinite(v):
                raise GeometryError(f"CArm.{name} must be finite, got {v}")
            object.__setattr__(self, name, v)
        try:
            shape = tuple(int(s) for s in self.shape)
        except (TypeError, ValueError):
            raise GeometryError(f"CArm.shape must be (rows, cols), got {self.shape!r}") from None
        if len(shape) != 2 or min(shape) < 2:
            raise GeometryError(f"CArm.shape must be (rows, cols) with both >= 2, got {self.shape}")
        object.__setattr__(self, "shape", shape)
        if self.sod_mm <= 0:
            raise GeometryError(f"DistanceSourceToPatient must be positive, got {self.sod_mm}")
        if self.sid_mm <= self.sod_mm:
            raise GeometryError(
                f"DistanceSourceToDetector must exceed DistanceSourceToPatient, "
                f"got {self.sid_mm} <= {self.sod_mm}"
            )
        if self.pixel_mm <= 0:
            raise GeometryError(f"ImagerPixelSpacing must be positive, got {self.pixel_mm}")
        if abs(self.primary_deg) > 180 or abs(self.secondary_deg) > 90:
            raise GeometryError(
                f"positioner angles out of range: primary {self.primary_deg} (|.|<=180), "
                f"secondary {self.secondary_deg} (|.|<=90)"
            )

    # --- frame ---------------------------------------------------------------------------
    @property
    def rows(self) -> int:
        return self.shape[0]

    @property
    def cols(self) -> int:
        return self.shape[1]

    @property
    def axes(self) -> np.ndarray:
        """``(3, 3)`` rows ``(e_u, e_v, d)`` in the room frame (det = -1)."""
        a, b = np.radians(self.primary_deg), np.radians(self.secondary_deg)
        sa, ca, sb, cb = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
        e_u = [ca, sa, 0.0]
        e_v = [sb * sa, -sb * ca, -cb]
        d = [sa * cb, -ca * cb, sb]
        return np.array([e_u, e_v, d])

    @property
    def beam_direction(self) -> np.ndarray:
        return self.axes[2]

    @property
    def source_room_mm(self) -> np.ndarray:
        return -self.sod_mm * self.beam_direction

    @property
    def detector_centre_room_mm(self) -> np.ndarray:
        return (self.sid_mm - self.sod_mm) * self.beam_direction

    @property
    def focal_px(self) -> float:
        return self.sid_mm / self.pixel_mm

    @property
    def principal_point_px(self) -> np.ndarray:
        return np.array([(self.cols - 1) / 2.0, (self.rows - 1) / 2.0])

    @property
    def magnification(self) -> float:
        """Magnification at the isocentre (SID / SOD)."""
        return self.sid_mm / self.sod_mm

    @property
    def pixel_at_iso_mm(self) -> float:
        """Size of one detector pixel back-projected to the isocentre plane."""
        return self.pixel_mm / self.magnification

    def intrinsics(self) -> np.ndarray:
        f = self.focal_px
        cu, cv = self.principal_point_px
        return np.array([[f, 0.0, cu], [0.0, f, cv], [0.0, 0.0, 1.0]])

    def extrinsics(self, pose: Pose | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(R_cam, t_cam)`` with ``x_cam = R_cam @ x_lps + t_cam`` (z = depth along the beam)."""
        pose = Pose.identity() if pose is None else pose
        R = self.axes
        S = self.source_room_mm
        # x_cam = R (T x - S) = R Rp x + R (tp - S)
        return R @ pose.R, R @ (pose.t - S)

    def projection_matrix(self, pose: Pose | None = None) -> np.ndarray:
        """``(3, 4)`` matrix: homogeneous LPS mm -> homogeneous ``(u, v)`` px."""
        Rc, tc = self.extrinsics(pose)
        return self.intrinsics() @ np.hstack([Rc, tc[:, None]])

    # --- projection ----------------------------------------------------------------------
    def to_camera(self, points_lps_mm, pose: Pose | None = None) -> np.ndarray:
        Rc, tc = self.extrinsics(pose)
        return np.asarray(points_lps_mm, dtype=float) @ Rc.T + tc

    def project(self, points_lps_mm, pose: Pose | None = None, *, return_depth: bool = False):
        """Project ``(N, 3)`` LPS points to ``(N, 2)`` pixel ``(u, v)``.

        With ``return_depth``, also returns the depth in mm along the beam from the source.
        Points at or behind the source get NaN pixels.
        """
        pts = np.asarray(points_lps_mm, dtype=float)
        single = pts.ndim == 1
        pts = np.atleast_2d(pts)
        xc = self.to_camera(pts, pose)
        z = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = self.focal_px * xc[:, :2] / z[:, None] + self.principal_point_px
        uv[z <= _EPS] = np.nan
        if single:
            uv, z = uv[0], z[0]
        return (uv, z) if return_depth else uv

    def rays(self, uv_px, pose: Pose | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels to rays in LPS: ``(origins (N, 3), unit directions (N, 3))``.

        Every origin is the X-ray source; ``origin + s * direction`` projects to ``uv``.
        """
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        pose = Pose.identity() if pose is None else pose
        Rc, tc = self.extrinsics(pose)
        ray_cam = np.column_stack(
            [(uv - self.principal_point_px) / self.focal_px, np.ones(len(uv))]
        )
        dirs = ray_cam @ Rc  # R_cam^T applied to each row
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origin = -Rc.T @ tc
        return np.repeat(origin[None, :], len(uv), axis=0), dirs

    def backproject(self, uv_px, depth_mm, pose: Pose | None = None) -> np.ndarray:
        """Points in LPS at camera depth ``depth_mm`` (along the beam axis) on each pixel's ray."""
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        z = np.broadcast_to(np.asarray(depth_mm, dtype=float), (len(uv),))
        xc = np.column_stack([(uv - self.principal_point_px) / self.focal_px * z[:, None], z])
        Rc, tc = self.extrinsics(pose)
        return (xc - tc) @ Rc

    def source_lps_mm(self, pose: Pose | None = None) -> np.ndarray:
        pose = Pose.identity() if pose is None else pose
        return pose.inverse().apply(self.source_room_mm)

    def detector_corners_lps_mm(self, pose: Pose | None = None) -> np.ndarray:
        """``(4, 3)`` LPS corners of the detector's outer pixel edges: (0,0), (W,0), (W,H), (0,H)."""
        pose = Pose.identity() if pose is None else pose
        e_u, e_v, _ = self.axes
        D = self.detector_centre_room_mm
        cu, cv = self.principal_point_px
        corners = []
        for u, v in ((-0.5, -0.5), (self.cols - 0.5, -0.5), (self.cols - 0.5, self.rows - 0.5), (-0.5, self.rows - 0.5)):
            corners.append(D + (u - cu) * self.pixel_mm * e_u + (v - cv) * self.pixel_mm * e_v)
        return pose.inverse().apply(np.array(corners))

    def in_image(self, uv_px, *, margin_px: float = 0.0) -> np.ndarray:
        uv = np.atleast_2d(np.asarray(uv_px, dtype=float))
        return (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= -0.5 + margin_px)
            & (uv[:, 0] <= self.cols - 0.5 - margin_px)
            & (uv[:, 1] >= -0.5 + margin_px)
            & (uv[:, 1] <= self.rows - 0.5 - margin_px)
        )

    def to_dict(self) -> dict:
        return {
            "primary_deg": self.primary_deg,
            "secondary_deg": self.secondary_deg,
            "sid_mm": self.sid_mm,
            "sod_mm": self.sod_mm,
            "pixel_mm": self.pixel_mm,
            "shape": list(self.shape),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "CArm":
        try:
            return cls(
                primary_deg=d["primary_deg"],
                secondary_deg=d["secondary_deg"],
                sid_mm=d["sid_mm"],
                sod_mm=d["sod_mm"],
                pixel_mm=d["pixel_mm"],
                shape=tuple(d["shape"]),
            )
        except KeyError as e:
            raise GeometryError(f"C-arm geometry is missing field {e.args[0]!r}") from None


def nominal_pose(centroid_lps_mm) -> Pose:
    """The registration's starting pose: the isocentre at the given centroid, no rotation."""
    return Pose(np.eye(3), -np.asarray(centroid_lps_mm, dtype=float))


__all__ += ["nominal_pose"]
