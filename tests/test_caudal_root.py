"""The automatic tree's default root: where a transfemoral wire enters an aortic tree
(``vesseltree.caudal_access_end``, ``rooted_at_caudal_end``), on hand-built trees whose true entry is known."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from guidewire3d.app.vesselplan import root_rule, tree_notes
from guidewire3d.vesseltree import (ACCESS_PATH_MIN_RADIUS_MM, AORTIC_RADIUS_MM, VesselTree, caudal_access_end,
                                    rooted_at_caudal_end)


class _Builder:
    """Polylines joined into one tree (LPS mm, +z superior), each new one hanging off an existing point."""

    def __init__(self, start, radius):
        self.P, self.R, self.par = [np.asarray(start, float)], [float(radius)], [-1]

    def line(self, frm: int, to, radius_from, radius_to, step_mm: float = 2.0) -> list[int]:
        a, b = self.P[frm], np.asarray(to, float)
        n = max(int(np.ceil(np.linalg.norm(b - a) / step_mm)), 1)
        ids, prev = [], frm
        for k in range(1, n + 1):
            f = k / n
            self.P.append(a + f * (b - a))
            self.R.append(radius_from + f * (radius_to - radius_from))
            self.par.append(prev)
            prev = len(self.P) - 1
            ids.append(prev)
        return ids

    def tree(self) -> VesselTree:
        return VesselTree(np.array(self.P), np.array(self.R), np.array(self.par))


def _aorta(with_iliacs: bool = False):
    """An aortic root (14 mm) at z = 0 whose arch turns down into a descending aorta (10 -> 8 mm) to z = -300, with
    a carotid (4 mm) up to z = +80, intercostals (1.5 mm) reaching lower than the aorta, a superior mesenteric artery
    (3 mm) alongside it to z = -305, and the aorta's lower end forked into thin strands (1 mm), as a lumen cut by the
    field of view's edge ends; with ``with_iliacs``, iliac and femoral arteries (5 -> 3.5 mm) to z = -520 instead."""
    b = _Builder((0, 0, 0), 14.0)
    asc = b.line(0, (0, 0, 40), 14.0, 12.0)
    arch = b.line(asc[-1], (0, 40, 60), 12.0, 11.0)
    b.line(arch[len(arch) // 2], (0, 30, 140), 4.0, 3.5)  # a carotid, up out of the view
    desc = b.line(arch[-1], (0, 60, -300), 10.0, 8.0)
    for k, i in enumerate(desc[::20][1:]):  # intercostals
        b.line(i, (30 * (-1) ** k, 70, b.P[i][2] - 60), 1.5, 1.0)
    sma_from = min(desc, key=lambda i: abs(b.P[i][2] + 200))
    b.line(sma_from, (0, 30, -305), 3.0, 2.8)
    if with_iliacs:
        for side in (-1, 1):
            b.line(desc[-1], (side * 40, 60, -520), 5.0, 3.5)
    else:
        for side in (-1, 1):
            b.line(desc[-1], (side * 4, 60, -306), 1.0, 0.8)
    return b, desc


def test_an_aortic_tree_is_rooted_at_its_aortas_caudal_end():
    b, desc = _aorta()
    tree = b.tree()
    assert tree.root == 0 and tree.radius_mm[0] == tree.radius_mm.max()  # the widest end: the aortic root
    end = caudal_access_end(tree)
    # the descending aorta's last point: not the strands' tips (1 mm), the lower intercostal ends (1.5 mm) or the
    # superior mesenteric artery's end (3 mm, 5 mm lower: within the tie, on a narrower path)
    assert end == desc[-1], (end, tree.points_lps_mm[end])
    z = tree.points_lps_mm[:, 2]
    assert z.min() < z[end] - 15  # the intercostals reach lower
    rooted = rooted_at_caudal_end(tree)
    assert rooted.root == end
    assert root_rule(rooted, seeded=False, access=False).startswith("the lower end of the aorta")
    assert root_rule(tree, seeded=False, access=False) == "the widest end"  # what vessels.json would say before
    # what `vessels` and the Slicer module say of it
    auto = SimpleNamespace(fallback="", first_pass_problems=(), pruned="", bias_field="", seeded="",
                           vessels=SimpleNamespace(tree=rooted, cut_through_lps_mm=()))
    assert any("rooted at the lower end of its aorta" in n and "--access-lps" in n for n in tree_notes(auto))
    assert not tree_notes(SimpleNamespace(fallback="", first_pass_problems=(), pruned="", bias_field="", seeded="",
                                          vessels=SimpleNamespace(tree=tree, cut_through_lps_mm=())))
    np.testing.assert_array_equal(rooted.points_lps_mm, tree.points_lps_mm)
    assert {tuple(sorted(e)) for e in rooted.edges.tolist()} == {tuple(sorted(e)) for e in tree.edges.tolist()}


def test_with_iliac_arteries_in_view_the_root_is_at_a_femoral_end():
    b, _ = _aorta(with_iliacs=True)
    tree = b.tree()
    end = caudal_access_end(tree)
    p = tree.points_lps_mm[end]
    assert abs(p[2] + 520) < 1e-6 and abs(abs(p[0]) - 40) < 1e-6, p
    assert tree.radius_mm[end] >= ACCESS_PATH_MIN_RADIUS_MM


def test_a_tree_without_an_aorta_keeps_its_root():
    # a coronary tree: ostium 2.4 mm, branches reaching lower than it
    b = _Builder((0, 0, 0), 2.4)
    main = b.line(0, (0, 40, -60), 2.4, 1.5)
    b.line(main[10], (30, 40, -90), 1.8, 1.0)
    tree = b.tree()
    assert tree.radius_mm.max() < AORTIC_RADIUS_MM
    assert caudal_access_end(tree) is None
    assert rooted_at_caudal_end(tree) is tree
