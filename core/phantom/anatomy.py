"""The simulator's anatomy: the CT grid, a random vessel tree, its lumen, and the guidewire's path in it.

* **Vessel tree** (LPS mm): a trunk (radius about 3 mm) and 2-3 levels of branches grown as
  smooth tortuous curves (an Ornstein-Uhlenbeck process on the curvature vector), radii tapering
  along each branch down to about 0.8 mm, bifurcation angles 30-75 degrees. Branches that leave
  the CT box are cut there, in the truth tree too.
* **Lumen**: the union of the tubes (capsules with linearly varying radius) around the centerline
  segments; :func:`lumen_depth_mm` is its signed depth (positive inside).
* **Guidewire**: follows one root-to-leaf path; it rides on the outer side of bends, cuts the
  corner where the path turns into a side branch, wanders smoothly off-centre elsewhere, and keeps
  at least ``wire radius + WIRE_MARGIN_MM`` (or the catheter's outer radius) inside the wall.
  Over the frames its tip advances distally (``guidewire3d.phantom.case.simulate``); the proximal
  end stays at the trunk's start.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from guidewire3d.errors import GeometryError
from guidewire3d.vesseltree import VesselTree
from scipy import ndimage

__all__ = ["VolumeSize", "lumen_depth_mm", "WIRE_DIAMETERS_MM", "WIRE_MARGIN_MM", "WIRE_STEP_MM", "TREE_STEP_MM"]

#: 0.014" and 0.035" guidewires
WIRE_DIAMETERS_MM = (0.36, 0.89)
#: clearance kept between the wire (or catheter) surface and the lumen wall
WIRE_MARGIN_MM = 0.1
#: spacing of the truth wire points along the wire
WIRE_STEP_MM = 0.25
#: growth step of the centerline (spacing of the truth tree points)
TREE_STEP_MM = 0.5


class VolumeSize(str, Enum):
    """CT grid size: ``SMALL`` about 160x160x(100-140) voxels, ``LARGE`` 512x512x300."""

    SMALL = "small"
    LARGE = "large"


# ======================================================================================
# vectors
# ======================================================================================
def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _perp_unit(t, rng) -> np.ndarray:
    a = _unit(rng.normal(size=3))
    a = a - (a @ t) * t
    if np.linalg.norm(a) < 1e-3:
        a = np.cross(t, [1.0, 0.0, 0.0]) if abs(t[0]) < 0.9 else np.cross(t, [0.0, 1.0, 0.0])
    return _unit(a)


# ======================================================================================
# CT grid
# ======================================================================================
@dataclass(frozen=True)
class _Grid:
    shape_zyx: tuple[int, int, int]
    spacing_xyz: tuple[float, float, float]
    origin_xyz: tuple[float, float, float]

    @property
    def lo(self) -> np.ndarray:
        return np.asarray(self.origin_xyz, float)

    @property
    def hi(self) -> np.ndarray:
        nz, ny, nx = self.shape_zyx
        return self.lo + (np.array([nx, ny, nz]) - 1) * np.asarray(self.spacing_xyz)


def _sample_grid(rng, volume: VolumeSize) -> tuple[_Grid, np.ndarray, np.ndarray]:
    """CT grid and the box (lo, hi) in which the tree grows."""
    sxy = round(float(rng.uniform(0.5, 0.8)), 4)
    sz = round(float(rng.uniform(0.6, 1.25)), 4)
    origin = (
        round(float(rng.uniform(-140.0, -40.0)), 3),
        round(float(rng.uniform(-160.0, -60.0)), 3),
        round(float(rng.uniform(-450.0, -80.0)), 3),
    )
    if volume is VolumeSize.SMALL:
        nz = int(np.clip(round(rng.uniform(95.0, 140.0) / sz), 100, 140))
        grid = _Grid((nz, 160, 160), (sxy, sxy, sz), origin)
        return grid, grid.lo + 3.0, grid.hi - 3.0
    grid = _Grid((300, 512, 512), (sxy, sxy, sz), origin)
    ext = grid.hi - grid.lo
    size = np.minimum([115.0, 115.0, 130.0], ext - 10.0)
    centre = grid.lo + ext / 2 + rng.uniform(-0.12, 0.12, 3) * (ext - size)
    return grid, centre - size / 2, centre + size / 2


# ======================================================================================
# vessel tree
# ======================================================================================
def _grow(rng, start, direction, length_mm, r0, r1, lo, hi, tortuosity):
    """One tortuous branch from ``start``: (n, 3) points at TREE_STEP_MM and (n,) radii."""
    step = TREE_STEP_MM
    n = max(int(length_mm / step), 4)
    pts = np.empty((n + 1, 3))
    pts[0] = start
    d = _unit(direction)
    k = np.zeros(3)
    corr = rng.uniform(8.0, 20.0)
    a = np.exp(-step / corr)
    margin = 8.0
    gain = 0.08
    noise = rng.normal(size=(n, 3)) * tortuosity * np.sqrt(1 - a * a)
    for i in range(n):
        k = a * k + noise[i]
        p = pts[i]
        steer = np.clip((margin - (p - lo)) / margin, 0, None) - np.clip((margin - (hi - p)) / margin, 0, None)
        kk = k + gain * steer
        kk = kk - (kk @ d) * d
        d = _unit(d + kk * step)
        pts[i + 1] = p + d * step
    s = np.linspace(0.0, 1.0, n + 1)
    radii = r0 + (r1 - r0) * s
    return pts, radii


def _grow_tree(rng, lo, hi):
    """Polylines, radii, parents ((branch, point index) or None) and levels of a random tree."""
    ext = hi - lo
    tort = rng.uniform(0.02, 0.06)
    # the trunk enters through a face of the box (mostly the superior or inferior one)
    axis = int(rng.choice([2, 2, 2, 1, 0]))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    start = lo + ext * rng.uniform(0.3, 0.7, 3)
    start[axis] = lo[axis] + 0.5 if sign > 0 else hi[axis] - 0.5
    d0 = np.zeros(3)
    d0[axis] = sign
    d0 = _unit(d0 + 0.35 * _perp_unit(d0, rng) * rng.uniform(0.2, 1.0))
    trunk_len = rng.uniform(0.75, 0.95) * ext[axis]
    r_trunk = rng.uniform(2.6, 3.2)
    polys, radii, parents, levels = [], [], [], []
    p, r = _grow(rng, start, d0, trunk_len, r_trunk, r_trunk * rng.uniform(0.65, 0.85), lo, hi, 0.6 * tort)
    polys.append(p), radii.append(r), parents.append(None), levels.append(0)
    size = float(np.mean(ext))
    spec = {  # level: (children per parent, length fraction of box, end radius range)
        1: ((2, 4), (0.45, 0.8), (1.0, 1.5)),
        2: ((1, 3), (0.3, 0.5), (0.8, 1.1)),
        3: ((1, 2), (0.15, 0.3), (0.8, 0.85)),
    }
    queue = [0]
    while queue:
        b = queue.pop(0)
        lev = levels[b] + 1
        if lev > 3:
            continue
        if lev == 3 and rng.random() < 0.4:
            continue
        (nmin, nmax), (fl, fh), (re_lo, re_hi) = spec[lev]
        n_child = int(rng.integers(nmin, nmax + 1))
        parent_pts, parent_r = polys[b], radii[b]
        n_par = len(parent_pts)
        fracs = np.sort(rng.uniform(0.2, 0.85, n_child))
        for j in range(1, n_child):  # keep bifurcations apart
            fracs[j] = max(fracs[j], fracs[j - 1] + 12.0 / (n_par * TREE_STEP_MM))
        az0 = rng.uniform(0, 2 * np.pi)
        for j, f in enumerate(fracs):
            idx = int(f * (n_par - 1))
            if idx < 2 or idx > n_par - 6:
                continue
            t = _unit(parent_pts[idx + 1] - parent_pts[idx - 1])
            u = _perp_unit(t, rng)
            w = np.cross(t, u)
            az = az0 + 2 * np.pi * j / max(n_child, 1) + rng.uniform(-0.6, 0.6)
            axis_perp = np.cos(az) * u + np.sin(az) * w
            theta = np.radians(rng.uniform(30.0, 75.0))
            dirn = np.cos(theta) * t + np.sin(theta) * axis_perp
            r0 = max(parent_r[idx] * rng.uniform(0.6, 0.78), 0.95)
            r1 = min(rng.uniform(re_lo, re_hi), r0 - 0.05)
            length = rng.uniform(fl, fh) * size
            pc, rc = _grow(rng, parent_pts[idx], dirn, length, r0, max(r1, 0.8), lo, hi, tort)
            polys.append(pc), radii.append(rc), parents.append((b, idx)), levels.append(lev)
            queue.append(len(polys) - 1)
    return polys, radii, parents, levels


def _cut_tree(polys, radii, parents, levels, lo, hi):
    """Cut branches at the first point outside [lo, hi]; drop what hangs beyond a cut."""
    out_p, out_r, out_par, out_lev, cut = [], [], [], [], []
    new_index: dict[int, int] = {}
    for k, (pl, rr, pa, lev) in enumerate(zip(polys, radii, parents, levels)):
        if pa is not None:
            pb, pi = pa
            if pb not in new_index:
                continue
            nb = new_index[pb]
            if pi >= len(out_p[nb]) - 3:
                continue
            pa = (nb, pi)
        inside = np.all((pl >= lo) & (pl <= hi), axis=1)
        n_in = len(pl) if inside.all() else int(np.argmin(inside))
        if n_in < 8:
            if pa is None:
                return None
            continue
        new_index[k] = len(out_p)
        out_p.append(pl[:n_in]), out_r.append(rr[:n_in]), out_par.append(pa), out_lev.append(lev)
        cut.append(n_in < len(pl))
    offsets, n = [], 0
    for k, pl in enumerate(out_p):
        offsets.append(n)
        n += len(pl) if k == 0 else len(pl) - 1
    tree = VesselTree.from_polylines(out_p, out_r, out_par)
    leaf_ids = [offsets[k] + (len(pl) - 1 if k == 0 else len(pl) - 2) for k, pl in enumerate(out_p)]
    return tree, np.array(leaf_ids), np.array(out_lev), np.array(cut)


def _make_tree(rng, lo, hi, grid: _Grid):
    ct_lo, ct_hi = grid.lo + 0.5, grid.hi - 0.5
    for _ in range(50):
        polys, radii, parents, levels = _grow_tree(rng, lo, hi)
        res = _cut_tree(polys, radii, parents, levels, ct_lo, ct_hi)
        if res is None:
            continue
        tree, end_ids, lev, cut = res
        leaves = set(tree.leaves.tolist())
        if len(tree.branches) >= 5 and tree.total_length_mm > 200:
            return tree, {int(e): (int(lv), bool(c)) for e, lv, c in zip(end_ids, lev, cut) if int(e) in leaves}
    raise GeometryError("phantom: could not grow a vessel tree inside the CT box")  # pragma: no cover


# ======================================================================================
# lumen: signed depth of the union of tubes
# ======================================================================================
def lumen_depth_mm(tree: VesselTree, points_lps_mm, *, k_nearest: int = 64) -> np.ndarray:
    """Signed depth inside the lumen (mm; positive inside, negative outside) of ``(N, 3)`` points.

    The lumen is the union of tapered capsules around the tree's edges (the simulator's model);
    the depth is the largest ``radius(t) - distance to the edge axis`` over the edges near each
    point (the ``k_nearest`` nearest centreline points and their edges). Far from the tree the value
    is a lower bound of the true depth (i.e. it never overstates how deep a point is).
    """
    pts = np.atleast_2d(np.asarray(points_lps_mm, dtype=float))
    k = min(k_nearest, tree.n_points)
    _, idx = tree.kdtree.query(pts, k=k)
    idx = idx.reshape(len(pts), k)
    par = tree.parent[idx]
    best = np.full(len(pts), -np.inf)
    P, R = tree.points_lps_mm, tree.radius_mm
    for j in range(k):
        i = idx[:, j]
        for other in (par[:, j], None):
            if other is None:  # the edges to the children are covered as the children's edges
                d = R[i] - np.linalg.norm(pts - P[i], axis=1)
            else:
                ok = other >= 0
                o = np.where(ok, other, i)
                a, b = P[o], P[i]
                ab = b - a
                L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
                t = np.clip(np.einsum("ij,ij->i", pts - a, ab) / L2, 0, 1)
                q = a + t[:, None] * ab
                d = R[o] + (R[i] - R[o]) * t - np.linalg.norm(pts - q, axis=1)
            best = np.maximum(best, d)
    return best


def _every_other(ids: np.ndarray) -> np.ndarray:
    """Every second point id of a branch, and its last: the coarser segments of the CT and the roadmap."""
    if len(ids) <= 2:
        return ids
    keep = np.r_[ids[:-1:2], ids[-1]]
    return keep


# ======================================================================================
# guidewire
# ======================================================================================
def _resample(points, step):
    p = np.asarray(points, float)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    n = max(int(np.round(s[-1] / step)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.column_stack([np.interp(t, s, p[:, k]) for k in range(3)]), t, s


def _choose_path(rng, tree: VesselTree, leaf_info, clearance_mm):
    s = tree.arclength_from_root_mm
    cands, weights = [], []
    for leaf, (lev, cut) in leaf_info.items():
        if cut:
            continue
        ids = tree.path_to_root(leaf)
        if tree.radius_mm[ids].min() < clearance_mm + 0.15:
            continue
        cands.append(ids)
        weights.append((1.0 + lev) * s[leaf])
    if not cands:  # fall back to any leaf, cut or not
        for leaf in tree.leaves:
            ids = tree.path_to_root(int(leaf))
            cands.append(ids)
            weights.append(s[leaf])
    weights = np.asarray(weights, float)
    lengths = np.array([s[c[-1]] for c in cands])
    weights[lengths < 0.6 * lengths.max()] *= 0.05
    return cands[int(rng.choice(len(cands), p=weights / weights.sum()))]


def _wire_shape(rng, tree: VesselTree, path_ids, wire_r, cath_r, cath_len_mm):
    """The wire along the whole path (LPS, WIRE_STEP_MM apart) and the path's arclength mapping."""
    step = WIRE_STEP_MM
    P = tree.points_lps_mm[path_ids]
    R = tree.radius_mm[path_ids]
    c, s_new, s_old = _resample(P, step)
    r = np.interp(s_new, s_old, R)
    n = len(c)
    clear = np.full(n, wire_r + WIRE_MARGIN_MM)
    if cath_r > 0:
        clear[s_new <= cath_len_mm + 1.0] = cath_r + WIRE_MARGIN_MM
    rho = np.maximum(r - clear - 0.03, 0.0)
    # curvature of the (smoothed) centerline; normal points to the inner side of bends
    cs = ndimage.gaussian_filter1d(c, 3.0 / step, axis=0, mode="nearest")
    T = _unit(np.gradient(cs, step, axis=0))
    k = np.gradient(T, step, axis=0)
    k -= np.sum(k * T, axis=1, keepdims=True) * T
    kappa = np.linalg.norm(k, axis=1)
    nrm = k / np.maximum(kappa, 1e-9)[:, None]
    hug = rng.uniform(0.7, 1.0)
    outer = -nrm * (rho * hug * np.clip(kappa * rng.uniform(15, 30), 0, 1))[:, None]
    # smooth random wander in the cross-section
    wander = ndimage.gaussian_filter1d(rng.normal(size=(n, 3)), rng.uniform(6, 14) / step, axis=0, mode="nearest")
    wander -= np.sum(wander * T, axis=1, keepdims=True) * T
    wander = _unit(wander) * (rho * rng.uniform(0.2, 0.6))[:, None]
    offset = outer + wander
    # corners where the path turns into a side branch: the wire cuts them (inner side)
    w_corner = np.zeros(n)
    ch = tree.children
    for j in range(1, len(path_ids) - 1):
        node = path_ids[j]
        if len(ch[node]) < 2:
            continue
        t_in = _unit(P[j] - P[max(j - 4, 0)])
        t_out = _unit(P[min(j + 4, len(P) - 1)] - P[j])
        if np.degrees(np.arccos(np.clip(t_in @ t_out, -1, 1))) < 15:
            continue
        sb = np.interp(j, np.arange(len(P)), s_old)
        w_corner = np.maximum(w_corner, np.exp(-0.5 * ((s_new - sb) / 2.5) ** 2))
    inner = nrm * (rho * 0.9)[:, None]
    offset = (1 - w_corner)[:, None] * offset + w_corner[:, None] * inner
    mag = np.linalg.norm(offset, axis=1)
    offset *= (np.minimum(mag, rho) / np.maximum(mag, 1e-12))[:, None]
    # stiffness: the offsets vary smoothly, and kinks of the centreline (bifurcations) are rounded
    stiff = rng.uniform(1.0, 2.0) * (1.5 if wire_r > 0.3 else 1.0)
    offset = ndimage.gaussian_filter1d(offset, stiff / step, axis=0, mode="nearest")
    x = ndimage.gaussian_filter1d(c, 1.0 / step, axis=0, mode="nearest") + offset
    x = _project_into_spheres(x, c, rho)
    # uniform arclength, then make sure of the constraint again
    xr, _, _ = _resample(x, step)
    from scipy.spatial import cKDTree

    _, j = cKDTree(c).query(xr)
    xr = _project_into_spheres(xr, c[j], rho[j])
    # arclength along the path of each wire point (for the tip position per frame)
    return xr, s_new[j]


def _project_into_spheres(x, c, rho):
    v = x - c
    d = np.linalg.norm(v, axis=1)
    f = np.where(d > rho, rho / np.maximum(d, 1e-12), 1.0)
    return c + v * f[:, None]
