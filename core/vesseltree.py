"""The 3D vessel centerline graph shared by every stage (what ``guidewire3d.cta.centerline`` builds).

A ``VesselTree`` is a rooted tree over centerline points: ``parent[i]`` is the index of the
point one step closer to the root (``-1`` for the root). Branches (runs between the root,
bifurcations and leaves) are derived from it, ordered root -> leaves.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from guidewire3d.errors import InputError
from scipy.sparse.csgraph import dijkstra

__all__ = ["Branch", "VesselTree", "ACCESS_PATH_MIN_RADIUS_MM", "AORTIC_RADIUS_MM", "CAUDAL_TIE_MM",
           "MAX_ACCESS_DISTANCE_MM", "access_record", "caudal_access_end", "check_access", "is_rooted_at_caudal_end",
           "SEED_END_WIDTH_TIE", "rooted_at_access", "rooted_at_caudal_end", "rooted_for_seed", "seed_end"]


@dataclass(frozen=True, eq=False)
class Branch:
    """One branch: ``point_ids`` run from its proximal node (shared with the parent) to its end."""

    index: int
    point_ids: np.ndarray
    parent: int  # branch index, -1 for the root branch
    children: tuple[int, ...]

    @property
    def is_leaf(self) -> bool:
        return not self.children


@dataclass(frozen=True, eq=False)
class VesselTree:
    """Centerline points (LPS mm) with radii, connected as a tree rooted at ``root``."""

    points_lps_mm: np.ndarray  # (N, 3)
    radius_mm: np.ndarray  # (N,)
    parent: np.ndarray  # (N,) int, -1 at the root
    #: how far the centerline may lie from the vessel's true axis, across the vessel (1 sigma per axis, mm), when
    #: known: a tree extracted from a CT's voxels carries its own (``cta.centerline.centerline_sigma_mm_of``); the
    #: reconstruction's uncertainty uses it where it exceeds ``ReconOptions.sigma_centerline_mm``. None: unknown
    centerline_sigma_mm: float | None = None
    #: (K, 3) LPS mm: segmented lumen of the tree's own mask that no ball of the tree covers (two vessels fused in
    #: the mask, the tree kept one: ``cta.lostlumen``), on a grid of step ``lost_lumen_step_mm``; None: unknown
    #: (a tree not extracted from a mask), an empty array: none
    lost_lumen_lps_mm: np.ndarray | None = None
    lost_lumen_step_mm: float | None = None

    def __post_init__(self):
        p = np.array(self.points_lps_mm, dtype=float, copy=True)
        r = np.array(self.radius_mm, dtype=float, copy=True).reshape(-1)
        par = np.array(self.parent, dtype=np.int64, copy=True).reshape(-1)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
            raise InputError(f"VesselTree needs (N>=2, 3) points, got {p.shape}")
        if r.shape != (len(p),) or par.shape != (len(p),):
            raise InputError("VesselTree radius_mm and parent must have one entry per point")
        if not np.all(np.isfinite(p)) or not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise InputError("VesselTree points must be finite and radii > 0")
        roots = np.flatnonzero(par < 0)
        if len(roots) != 1:
            raise InputError(f"VesselTree must have exactly one root, got {len(roots)}")
        if np.any(par >= len(p)):
            raise InputError("VesselTree parent index out of range")
        if self.centerline_sigma_mm is not None:
            try:
                cs = float(self.centerline_sigma_mm)
            except (TypeError, ValueError):
                raise InputError(f"VesselTree centerline_sigma_mm must be a number, got {self.centerline_sigma_mm!r}") from None
            if not np.isfinite(cs) or cs < 0:
                raise InputError(f"VesselTree centerline_sigma_mm must be finite and >= 0, got {cs}")
            object.__setattr__(self, "centerline_sigma_mm", cs)
        if self.lost_lumen_lps_mm is not None:
            q = np.array(self.lost_lumen_lps_mm, dtype=float, copy=True).reshape(-1, 3)
            try:
                st = float(self.lost_lumen_step_mm)
            except (TypeError, ValueError):
                raise InputError(f"VesselTree lost_lumen_step_mm must be a number, got {self.lost_lumen_step_mm!r}") \
                    from None
            if not np.all(np.isfinite(q)) or not np.isfinite(st) or st <= 0:
                raise InputError("VesselTree lost lumen points must be finite and its step > 0")
            q.setflags(write=False)
            object.__setattr__(self, "lost_lumen_lps_mm", q)
            object.__setattr__(self, "lost_lumen_step_mm", st)
        for a in (p, r, par):
            a.setflags(write=False)
        object.__setattr__(self, "points_lps_mm", p)
        object.__setattr__(self, "radius_mm", r)
        object.__setattr__(self, "parent", par)
        # reject cycles: every point must reach the root
        depth = self.depth_from_root
        if np.any(depth < 0):
            raise InputError("VesselTree parent links contain a cycle")

    # --- basic structure ----------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return len(self.points_lps_mm)

    @cached_property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    @cached_property
    def children(self) -> list[list[int]]:
        ch: list[list[int]] = [[] for _ in range(self.n_points)]
        for i, pa in enumerate(self.parent):
            if pa >= 0:
                ch[pa].append(i)
        return ch

    @cached_property
    def order(self) -> np.ndarray:
        """Point indices in breadth-first order from the root (parents before children)."""
        out = [self.root]
        k = 0
        while k < len(out):
            out.extend(self.children[out[k]])
            k += 1
        return np.array(out, dtype=np.int64)

    @cached_property
    def depth_from_root(self) -> np.ndarray:
        """Number of edges from the root to each point (-1 if unreachable)."""
        d = -np.ones(self.n_points, dtype=np.int64)
        ch: list[list[int]] = [[] for _ in range(self.n_points)]
        for i, pa in enumerate(self.parent):
            if pa >= 0:
                ch[pa].append(i)
        root = int(np.flatnonzero(self.parent < 0)[0])
        d[root] = 0
        stack = [root]
        while stack:
            i = stack.pop()
            for c in ch[i]:
                d[c] = d[i] + 1
                stack.append(c)
        return d

    @cached_property
    def edges(self) -> np.ndarray:
        """``(N - 1, 2)`` point-index pairs ``(parent, child)``."""
        child = np.flatnonzero(self.parent >= 0)
        return np.column_stack([self.parent[child], child])

    @cached_property
    def edge_length_mm(self) -> np.ndarray:
        e = self.edges
        return np.linalg.norm(self.points_lps_mm[e[:, 1]] - self.points_lps_mm[e[:, 0]], axis=1)

    @cached_property
    def length_at_point_mm(self) -> np.ndarray:
        """``(N,)`` the length of each point's edge to its parent (0 at the root): the tree's length
        counted per point, so that a subset of points has ``length_at_point_mm[subset].sum()``."""
        seg = np.zeros(self.n_points)
        seg[self.edges[:, 1]] = self.edge_length_mm
        seg.setflags(write=False)
        return seg

    @cached_property
    def arclength_from_root_mm(self) -> np.ndarray:
        s = np.zeros(self.n_points)
        seg = self.length_at_point_mm
        for i in self.order[1:]:
            s[i] = s[self.parent[i]] + seg[i]
        return s

    @cached_property
    def degree(self) -> np.ndarray:
        deg = np.zeros(self.n_points, dtype=np.int64)
        e = self.edges
        np.add.at(deg, e[:, 0], 1)
        np.add.at(deg, e[:, 1], 1)
        return deg

    @property
    def leaves(self) -> np.ndarray:
        return np.array([i for i in range(self.n_points) if not self.children[i]], dtype=np.int64)

    @property
    def bifurcations(self) -> np.ndarray:
        return np.array([i for i in range(self.n_points) if len(self.children[i]) >= 2], dtype=np.int64)

    @cached_property
    def branches(self) -> tuple[Branch, ...]:
        """Runs between nodes (root, bifurcations, leaves), ordered root -> leaves."""
        out: list[dict] = []
        # (start node, first child, parent branch)
        stack = [(self.root, c, -1) for c in reversed(self.children[self.root])]
        while stack:
            start, nxt, parent_branch = stack.pop()
            ids = [start, nxt]
            while len(self.children[ids[-1]]) == 1:
                ids.append(self.children[ids[-1]][0])
            idx = len(out)
            out.append({"ids": np.array(ids, dtype=np.int64), "parent": parent_branch, "children": []})
            if parent_branch >= 0:
                out[parent_branch]["children"].append(idx)
            for c in reversed(self.children[ids[-1]]):
                stack.append((ids[-1], c, idx))
        return tuple(
            Branch(index=i, point_ids=b["ids"], parent=b["parent"], children=tuple(b["children"]))
            for i, b in enumerate(out)
        )

    @cached_property
    def point_branch(self) -> np.ndarray:
        """Branch index of each point (a node belongs to the branch that ends at it)."""
        pb = np.zeros(self.n_points, dtype=np.int64)
        for b in self.branches:
            pb[b.point_ids[1:]] = b.index
        pb[self.root] = 0
        return pb

    @property
    def centroid_lps_mm(self) -> np.ndarray:
        return self.points_lps_mm.mean(axis=0)

    @property
    def total_length_mm(self) -> float:
        return float(self.edge_length_mm.sum())

    # --- graph queries ------------------------------------------------------------------
    @cached_property
    def adjacency(self) -> sp.csr_matrix:
        e = self.edges
        w = np.maximum(self.edge_length_mm, 1e-9)
        n = self.n_points
        A = sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
        return A.tocsr()

    def geodesic_mm(self, sources) -> np.ndarray:
        """Geodesic distances along the tree from each source point index: ``(len(sources), N)``."""
        return dijkstra(self.adjacency, directed=False, indices=np.atleast_1d(sources))

    def path_to_root(self, i: int) -> np.ndarray:
        """Point indices from the root to ``i`` (inclusive)."""
        out = [int(i)]
        while self.parent[out[-1]] >= 0:
            out.append(int(self.parent[out[-1]]))
        return np.array(out[::-1], dtype=np.int64)

    def path(self, i: int, j: int) -> np.ndarray:
        """Point indices along the tree from ``i`` to ``j`` (inclusive)."""
        a, b = self.path_to_root(i), self.path_to_root(j)
        n = min(len(a), len(b))
        k = 0
        while k < n and a[k] == b[k]:
            k += 1
        # a[k-1] == b[k-1] is the lowest common ancestor
        return np.concatenate([a[k - 1 :][::-1], b[k:]])

    def nearest_point(self, points_lps_mm) -> tuple[np.ndarray, np.ndarray]:
        """``(index, distance_mm)`` of the nearest centerline point for each query point."""
        dist, idx = self.kdtree.query(np.atleast_2d(np.asarray(points_lps_mm, dtype=float)))
        return idx, dist

    @cached_property
    def kdtree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.points_lps_mm)

    # --- conversion ---------------------------------------------------------------------
    def subtree(self, keep) -> "VesselTree":
        """The tree restricted to ``keep`` (bool mask or indices) which must include a connected part with the root."""
        keep_mask = np.zeros(self.n_points, bool)
        keep_mask[np.asarray(keep)] = True
        new_index = -np.ones(self.n_points, dtype=np.int64)
        new_index[keep_mask] = np.arange(keep_mask.sum())
        par = self.parent[keep_mask]
        new_par = np.where(par >= 0, new_index[np.maximum(par, 0)], -1)
        return VesselTree(self.points_lps_mm[keep_mask], self.radius_mm[keep_mask], new_par, **self._extras())

    def rerooted(self, new_root: int) -> "VesselTree":
        """The same points, radii and edges, rooted at point ``new_root`` (the edges on its path to the
        old root reversed)."""
        new_root = int(new_root)
        if not 0 <= new_root < self.n_points:
            raise InputError(f"VesselTree.rerooted: point {new_root} out of range (0..{self.n_points - 1})")
        if new_root == self.root:
            return self
        par = self.parent.copy()
        child, p = new_root, int(par[new_root])
        par[new_root] = -1
        while p >= 0:  # walk up to the old root, reversing each edge
            nxt = int(par[p])
            par[p] = child
            child, p = p, nxt
        return VesselTree(self.points_lps_mm, self.radius_mm, par, **self._extras())

    def densified(self, step_mm) -> tuple["VesselTree", np.ndarray]:
        """Insert points on edges longer than ``step_mm`` (scalar or per point, taken at the child).

        Original points keep their indices. Returns ``(dense tree, original id of each dense point)``.
        """
        tree = self
        n = tree.n_points
        e = tree.edges
        L = tree.edge_length_mm
        step = np.broadcast_to(np.asarray(step_mm, dtype=float), (n,))[e[:, 1]]
        k = np.maximum(np.ceil(L / step).astype(np.int64) - 1, 0)
        n_new = int(k.sum())
        if n_new == 0:
            return tree, np.arange(n, dtype=np.int64)
        P, R = tree.points_lps_mm, tree.radius_mm
        edge_of = np.repeat(np.arange(len(e)), k)
        first = np.r_[0, np.cumsum(k)[:-1]]
        local = np.arange(n_new) - np.repeat(first, k) + 1  # 1..k_e
        frac = local / (np.repeat(k, k) + 1.0)
        pa, ch = e[edge_of, 0], e[edge_of, 1]
        new_pts = P[pa] + frac[:, None] * (P[ch] - P[pa])
        new_rad = R[pa] + frac * (R[ch] - R[pa])
        new_ids = n + np.arange(n_new)
        new_par = np.where(local == 1, pa, new_ids - 1)
        parent = tree.parent.copy()
        last = new_ids[np.r_[first[k > 0] + k[k > 0] - 1]]
        parent[e[k > 0, 1]] = last
        orig = np.r_[np.arange(n), np.where(frac < 0.5, pa, ch)]
        dense = VesselTree(np.vstack([P, new_pts]), np.r_[R, new_rad], np.r_[parent, new_par], **tree._extras())
        return dense, orig.astype(np.int64)

    def transformed(self, pose) -> "VesselTree":
        """The same tree moved by a rigid ``Pose``."""
        ex = self._extras()
        if self.lost_lumen_lps_mm is not None and len(self.lost_lumen_lps_mm):
            ex["lost_lumen_lps_mm"] = pose.apply(self.lost_lumen_lps_mm)
        return VesselTree(pose.apply(self.points_lps_mm), self.radius_mm, self.parent, **ex)

    def _extras(self) -> dict:
        """What a tree derived from this one (the same vessels) keeps besides points, radii and parents."""
        return dict(centerline_sigma_mm=self.centerline_sigma_mm, lost_lumen_lps_mm=self.lost_lumen_lps_mm,
                    lost_lumen_step_mm=self.lost_lumen_step_mm)

    def with_lost_lumen(self, points_lps_mm, step_mm: float) -> "VesselTree":
        """The same tree carrying its lost lumen (``cta.lostlumen.lost_lumen_lps_mm``)."""
        return VesselTree(self.points_lps_mm, self.radius_mm, self.parent, self.centerline_sigma_mm,
                          np.asarray(points_lps_mm, float).reshape(-1, 3), step_mm)

    def to_dict(self) -> dict:
        d = {
            "points_lps_mm": np.round(self.points_lps_mm, 5).tolist(),
            "radius_mm": np.round(self.radius_mm, 5).tolist(),
            "parent": self.parent.tolist(),
        }
        if self.centerline_sigma_mm is not None:
            d["centerline_sigma_mm"] = round(self.centerline_sigma_mm, 5)
        if self.lost_lumen_lps_mm is not None:
            d["lost_lumen_lps_mm"] = np.round(self.lost_lumen_lps_mm, 3).tolist()
            d["lost_lumen_step_mm"] = round(float(self.lost_lumen_step_mm), 5)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VesselTree":
        try:
            lost = d.get("lost_lumen_lps_mm")
            return cls(np.asarray(d["points_lps_mm"]), np.asarray(d["radius_mm"]), np.asarray(d["parent"]),
                       d.get("centerline_sigma_mm"), None if lost is None else np.asarray(lost, float).reshape(-1, 3),
                       d.get("lost_lumen_step_mm") if lost is not None else None)
        except KeyError as e:
            raise InputError(f"vessel tree record is missing field {e.args[0]!r}") from None

    def to_polydata(self):
        """A VTK polyline per branch with point data ``radius_mm`` and ``branch`` (LPS mm)."""
        import vtk
        from vtk.util.numpy_support import numpy_to_vtk

        pts = vtk.vtkPoints()
        pts.SetData(numpy_to_vtk(np.ascontiguousarray(self.points_lps_mm), deep=True))
        lines = vtk.vtkCellArray()
        for b in self.branches:
            lines.InsertNextCell(len(b.point_ids))
            for i in b.point_ids:
                lines.InsertCellPoint(int(i))
        poly = vtk.vtkPolyData()
        poly.SetPoints(pts)
        poly.SetLines(lines)
        rad = numpy_to_vtk(np.ascontiguousarray(self.radius_mm), deep=True)
        rad.SetName("radius_mm")
        poly.GetPointData().AddArray(rad)
        poly.GetPointData().SetActiveScalars("radius_mm")
        br = numpy_to_vtk(np.ascontiguousarray(self.point_branch.astype(np.int32)), deep=True)
        br.SetName("branch")
        poly.GetPointData().AddArray(br)
        return poly

    @classmethod
    def from_polylines(cls, polylines, radii, parents) -> "VesselTree":
        """Build from branches given as polylines.

        ``polylines[k]`` is ``(n_k, 3)`` from proximal to distal; its first point is the attachment
        point. ``parents[k]`` is ``(branch, point_index_in_that_branch)`` or ``None`` for the root
        branch (which must be first). The attachment point of a child is snapped to the parent's
        point (the child's first point is dropped).
        """
        pts: list[np.ndarray] = []
        rad: list[np.ndarray] = []
        par: list[np.ndarray] = []
        offsets: list[int] = []
        n = 0
        for k, (pl, rr, pa) in enumerate(zip(polylines, radii, parents)):
            pl = np.asarray(pl, dtype=float)
            rr = np.asarray(rr, dtype=float)
            if pa is None:
                if k != 0:
                    raise InputError("only the first branch may be the root")
                p_local = np.arange(-1, len(pl) - 1) + n
                p_local[0] = -1
                pts.append(pl)
                rad.append(rr)
                par.append(p_local)
                offsets.append(n)
                n += len(pl)
            else:
                pb, pi = pa
                attach = offsets[pb] + (pi if pb == 0 else pi - 1)
                if pb != 0 and pi == 0:
                    raise InputError("cannot attach to a child branch's dropped first point")
                sub = pl[1:]
                p_local = np.arange(len(sub)) + n - 1
                p_local[0] = attach
                pts.append(sub)
                rad.append(rr[1:])
                par.append(p_local)
                offsets.append(n)
                n += len(sub)
        return cls(np.vstack(pts), np.concatenate(rad), np.concatenate(par))


# --------------------------------------------------------------------------------------
# the access point: where the wire enters the vessels
# --------------------------------------------------------------------------------------
#: An access point further than this from every point of the tree is refused. The tree is rooted at its
#: point nearest the access, which is the right point when the access lies beyond the end of the vessel
#: the wire comes up (a femoral puncture below an abdominal CTA, the sheath tip, a radial puncture beyond
#: the arm's field of view), but a point this far from every vessel is a point in another frame (RAS for
#: LPS), in other units or of another patient: refused, not guessed from. A femoral puncture below a chest
#: CTA (about 300 mm below its lower edge) is further: give the point where the wire enters the CTA then
#: (the descending aorta at the lower edge of the field of view).
MAX_ACCESS_DISTANCE_MM = 150.0


def _access_label(p, option: str) -> str:
    """``--access-lps=1,2,3`` for a command-line option, ``access point (1,2,3 LPS mm)`` otherwise."""
    xyz = ",".join(f"{v:g}" for v in p)
    return f"{option}={xyz}" if option.startswith("-") else f"{option} ({xyz} LPS mm)"


def check_access(access_lps_mm, *, bounds_lps_mm=None, max_distance_mm: float = MAX_ACCESS_DISTANCE_MM,
                 option: str = "--access-lps") -> np.ndarray:
    """The access point as a ``(3,)`` array, checked before any work.

    Parameters
    ----------
    access_lps_mm : (3,) array_like of float
        Where the wire enters the vessels (LPS mm).
    bounds_lps_mm : (2, 3) array_like of float, optional
        The CTA's LPS bounding box (``io.Volume.bounds_lps_mm``). Its vessel tree lies inside it, so an
        access point further than ``max_distance_mm`` from the box is further than that from the tree too:
        refused here, before the vessel stage.
    option : str
        The name the messages give the point (the command-line option).

    Raises
    ------
    InputError
        Not three finite numbers, or (with ``bounds_lps_mm``) too far from the CTA.
    """
    try:
        p = np.array(access_lps_mm, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{option}: expected a point x,y,z in LPS mm, got {access_lps_mm!r}") from None
    if p.shape != (3,):
        raise InputError(f"{option}: expected a point x,y,z in LPS mm, got {p.size} values")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{_access_label(p, option)}: not a finite point")
    if bounds_lps_mm is not None:
        lo, hi = np.asarray(bounds_lps_mm, dtype=float).reshape(2, 3)
        d = float(np.linalg.norm(np.maximum(lo - p, 0.0) + np.maximum(p - hi, 0.0)))
        if d > max_distance_mm:
            raise InputError(f"{_access_label(p, option)}: {d:.0f} mm outside the CTA's field of view, so at least "
                             f"that far from its vessels (at most {max_distance_mm:g} mm: give the point where the "
                             "wire enters the CTA, e.g. the sheath tip)")
    return p


def rooted_at_access(tree: VesselTree, access_lps_mm, *, max_distance_mm: float = MAX_ACCESS_DISTANCE_MM,
                     option: str = "--access-lps") -> VesselTree:
    """The tree rooted at its point nearest the access point, where the wire enters the vessels.

    The reconstruction and the live engine assume the wire is advanced from the tree's root (the
    automatic tree's root is the lower end of its aorta, :func:`rooted_at_caudal_end`, where a transfemoral
    wire enters; without an aorta its widest end); a transradial wire, or one from the other groin, comes from
    elsewhere. The points, radii and edges are those of ``tree``
    (:meth:`VesselTree.rerooted`); only the direction of the edges on the way to the new root changes.

    Parameters
    ----------
    tree : VesselTree
    access_lps_mm : (3,) array_like of float
        Where the wire enters (LPS mm): a puncture or the sheath tip. It may lie outside the CTA's
        field of view; the tree's nearest point is used then.
    max_distance_mm : float
        The farthest the access may be from the tree (:data:`MAX_ACCESS_DISTANCE_MM`).
    option : str
        The name the messages give the point (the command-line option).

    Returns
    -------
    VesselTree
        ``tree`` itself when its root is already the nearest point.

    Raises
    ------
    InputError
        Not three finite numbers, or further than ``max_distance_mm`` from every point of the tree.
    """
    p = check_access(access_lps_mm, max_distance_mm=max_distance_mm, option=option)
    idx, dist = tree.nearest_point(p)
    i, d = int(idx[0]), float(dist[0])
    if d > max_distance_mm:
        raise InputError(f"{_access_label(p, option)}: {d:.0f} mm from the nearest point of the vessel tree (at most "
                         f"{max_distance_mm:g} mm: give the point where the wire enters the CTA, e.g. the sheath tip)")
    return tree.rerooted(i)


def access_record(tree: VesselTree, access_lps_mm) -> dict:
    """What the output folders record of an access point (``report.json`` and ``vessels.json``
    ``"access"``): the point, the root chosen for it (the tree's root: a tree from
    :func:`rooted_at_access`) and the distance between them (mm)."""
    p = check_access(access_lps_mm)
    root = tree.points_lps_mm[tree.root]
    return {
        "access_lps_mm": [round(float(v), 3) for v in p],
        "root_index": int(tree.root),
        "root_lps_mm": [round(float(v), 3) for v in root],
        "distance_mm": round(float(np.linalg.norm(root - p)), 2),
        "max_distance_mm": MAX_ACCESS_DISTANCE_MM,
    }


#: A tree whose widest lumen has at least this radius holds an aorta (an adult's is 8-16 mm; an iliac or a
#: femoral artery at most 5-6 mm, a coronary 2.5 mm, the widest intracranial vessel, a dural sinus, 5 mm).
AORTIC_RADIUS_MM = 7.0
#: The path from the aorta to a transfemoral access end keeps at least this radius (a common femoral artery's
#: is 3-4 mm, a popliteal's 2.5-3): side branches (intercostal, lumbar, renal, mesenteric) narrow below it.
ACCESS_PATH_MIN_RADIUS_MM = 2.5
#: Ends within this of the most caudal one are taken as equally caudal; the widest path among them wins
#: (the descending aorta and the superior mesenteric artery both cut by the field of view's lower edge).
CAUDAL_TIE_MM = 10.0


def caudal_access_end(tree: VesselTree) -> int | None:
    """The point of an aortic tree where a transfemoral wire enters it: its most caudal point reached from its
    widest point along lumens no narrower than :data:`ACCESS_PATH_MIN_RADIUS_MM`; ``None`` for a tree without an
    aorta (widest radius below :data:`AORTIC_RADIUS_MM`).

    The groin is the commonest access of endovascular work (aortic, peripheral, neuro and most coronary
    procedures); a wire from there enters a chest or abdominal CTA's tree at the lower end of its aorta, or of an
    iliac or femoral artery when the field of view reaches them. The radius along a path is each branch's median
    (a partial-volume point does not break a lumen), the narrowest on the way from the widest point, the point's
    own branch included: a lumen cut by the field of view's edge ends in a fork of thin strands, and the point
    found is then where its wide part ends, not a strand's tip. Among the points within :data:`CAUDAL_TIE_MM` of
    the most caudal, those on the widest path win (the aorta, not the superior mesenteric artery beside it).
    """
    R = np.asarray(tree.radius_mm, float)
    if len(R) < 2 or not np.isfinite(R).any() or np.nanmax(R) < AORTIC_RADIUS_MM:
        return None
    t = tree.rerooted(int(np.nanargmax(R)))
    med = np.array([np.nanmedian(R[b.point_ids[1:]]) for b in t.branches])
    narrowest = np.zeros(len(t.branches))
    for b in t.branches:  # parents before children
        narrowest[b.index] = min(med[b.index], narrowest[b.parent] if b.parent >= 0 else np.inf)
    path_r = narrowest[t.point_branch]
    path_r[t.root] = R[t.root]
    wide = np.flatnonzero(path_r >= ACCESS_PATH_MIN_RADIUS_MM)
    z = tree.points_lps_mm[wide, 2]  # LPS: +z is superior
    low = wide[z <= z.min() + CAUDAL_TIE_MM]
    best = low[path_r[low] >= path_r[low].max()]
    return int(best[np.argmin(tree.points_lps_mm[best, 2])])


def is_rooted_at_caudal_end(tree: VesselTree) -> bool:
    """Whether ``tree`` holds an aorta and is rooted at :func:`caudal_access_end` (what ``vessels.json`` and the
    notes of ``vessels`` and the Slicer module say of its root)."""
    end = caudal_access_end(tree)  # None without an aorta
    return end is not None and end == tree.root


def rooted_at_caudal_end(tree: VesselTree) -> VesselTree:
    """``tree`` rooted at :func:`caudal_access_end` (itself when it has no aorta, or is rooted there already): the
    default root of an automatic tree, where a transfemoral wire comes from. ``--access-lps`` overrides it
    (:func:`rooted_at_access`)."""
    end = caudal_access_end(tree)
    return tree if end is None else tree.rerooted(end)


#: :func:`seed_end`: ends whose way out from the seed is at least this fraction as wide as the widest way out are
#: taken as equally wide, and the nearest of them along the tree wins (the seeded carotid's lower end, 2.4 mm, over
#: the other carotid's, reached through a 0.8 mm communicating artery).
SEED_END_WIDTH_TIE = 0.8


def seed_end(tree: VesselTree, seed_lps_mm) -> int:
    """The end of ``tree`` (its root or a leaf) where a wire enters, for a tree made from a seed: of the ends reached
    from the tree's point nearest the seed along the widest lumens (the narrowest branch on the way, each branch's
    median radius, at least :data:`SEED_END_WIDTH_TIE` of the widest way's), the nearest along the tree.

    Along the tree, not straight: a seed in a carotid in the neck is 30 mm from a vertebral artery's end across the
    neck, and 200 mm from it through the circle of Willis; the carotid's own lower end is 38 mm below the seed
    (the synthetic head, ``scripts/bench_head_cta.py --seed``). And along wide lumens: a thin side branch's end near
    the seed (an external carotid's, an intercostal's) is not where a wire comes from.
    """
    i, _ = tree.nearest_point(np.asarray(seed_lps_mm, dtype=float).reshape(3))
    t = tree.rerooted(int(i[0]))
    R = np.asarray(t.radius_mm, float)
    med = np.array([np.nanmedian(R[b.point_ids[1:]]) if len(b.point_ids) > 1 else R[b.point_ids[0]]
                    for b in t.branches])
    narrowest = np.zeros(len(t.branches))
    for b in t.branches:  # parents before children
        narrowest[b.index] = min(med[b.index], narrowest[b.parent] if b.parent >= 0 else np.inf)
    n_links = np.array([len(c) for c in t.children]) + (t.parent >= 0)
    ends = np.flatnonzero(n_links <= 1)
    path_r = np.nan_to_num(narrowest[t.point_branch[ends]], nan=0.0)
    wide = ends[path_r >= SEED_END_WIDTH_TIE * path_r.max()]
    d = t.geodesic_mm([t.root])[0]
    return int(wide[np.argmin(d[wide])])


def rooted_for_seed(tree: VesselTree, seed_lps_mm) -> VesselTree:
    """The default root of a tree made from seeds (``seed_lps_mm``, the first seed): where a transfemoral wire enters
    a tree that holds an aorta (:func:`rooted_at_caudal_end`, as without seeds: a seed says which tree, not where the
    wire comes from), else the end nearest the seed along its widest lumens (:func:`seed_end`). ``--access-lps``
    overrides both (:func:`rooted_at_access`)."""
    end = caudal_access_end(tree)
    return tree.rerooted(seed_end(tree, seed_lps_mm) if end is None else end)
