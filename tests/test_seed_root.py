"""The default root of a seeded tree (``vesseltree.seed_end``, ``rooted_for_seed``): an aortic tree's lower end, as
without seeds; else the end nearest the first seed *along the tree*, of those reached along its widest lumens. Until
stop 53 it was the end nearest the seed in a straight line: on the synthetic head, seeded in the left carotid in the
neck, a 2.6 mm spur of the left vertebral artery across the neck (30 mm away; 200 mm along the tree through the circle
of Willis), not the carotid's lower end.
Ground truth: hand-built trees whose entry is known, and the head phantom's arteries."""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from guidewire3d.app.vesselplan import root_rule, tree_notes
from guidewire3d.cta import vesselmodel
from guidewire3d.vesseltree import caudal_access_end, rooted_for_seed, seed_end

from test_caudal_root import _aorta, _Builder

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import bench_head_cta as H  # noqa: E402


def _neck():
    """A carotid (2.5 mm) from z = -90 up to z = 0, over to a circle at x = 0, and down a vertebral artery (1.8 mm)
    to its end at (20, 10, -60): 30 mm across the neck from the seed at (24, -8, -50), 260 mm along the tree."""
    b = _Builder((25, -10, -90), 2.5)
    ica = b.line(0, (25, -10, 0), 2.5, 2.0)
    circle = b.line(ica[-1], (0, 0, 10), 1.5, 1.5)
    b.line(circle[-1], (20, 10, -60), 1.8, 1.8)
    b.line(ica[len(ica) // 3], (40, -20, -55), 1.0, 0.8)  # a thin side branch (an external carotid's), its end
    # 22 mm from the seed along the tree, nearer than the carotid's lower end (40 mm)
    return b.tree()


def test_the_seeded_root_is_the_end_nearest_along_the_tree():
    tree = _neck()
    seed = np.array([24.0, -8.0, -50.0])
    vert_end = int(np.argmin(np.linalg.norm(tree.points_lps_mm - (20, 10, -60), axis=1)))
    straight = np.linalg.norm(tree.points_lps_mm[[0, vert_end]] - seed, axis=1)
    assert straight[1] < straight[0]  # the vertebral end is the nearer in a straight line (the old rule's root)
    assert seed_end(tree, seed) == 0  # along the tree: the carotid's lower end
    rooted = rooted_for_seed(tree.rerooted(vert_end), seed)
    assert rooted.root == 0
    np.testing.assert_array_equal(rooted.points_lps_mm, tree.points_lps_mm)
    assert root_rule(rooted, seeded=True, access=False) == "the end nearest the first seed along its widest lumens"
    side_end = int(np.argmin(np.linalg.norm(tree.points_lps_mm - (40, -20, -55), axis=1)))
    assert tree.geodesic_mm([tree.nearest_point(seed)[0][0]])[0][side_end] < 40.0
    # a seed in the thin branch itself: every way out is as thin, so its nearest end
    assert seed_end(tree, (38.0, -18.0, -56.0)) == side_end
    # a tree of equally wide ends: the nearest along the tree
    b = _Builder((0, 0, 0), 2.0)
    b.line(b.line(0, (0, 0, 50), 2.0, 2.0)[-1], (0, 40, 50), 2.0, 2.0)
    two = b.tree()
    assert seed_end(two, (0, 35, 51)) == two.n_points - 1 and seed_end(two, (1, 0, 10)) == 0


def test_a_seeded_aortic_tree_is_rooted_at_its_aortas_lower_end():
    b, desc = _aorta()
    tree = b.tree()
    seed = b.P[desc[5]] + (0, 0, 3.0)  # in the descending aorta near the arch: the arch's end is nearer along it
    assert seed_end(tree, seed) != desc[-1]
    rooted = rooted_for_seed(tree, seed)
    assert rooted.root == caudal_access_end(tree) == desc[-1]
    assert root_rule(rooted, seeded=True, access=False).startswith("the lower end of the aorta")
    for seeded in ("automatic tree", "seeds"):
        notes = tree_notes(SimpleNamespace(fallback="", first_pass_problems=(), pruned="", bias_field="", seeded=seeded,
                                           vessels=SimpleNamespace(tree=rooted, cut_through_lps_mm=())))
        assert any("rooted at the lower end of its aorta" in n for n in notes), notes
        assert not any("nearest the first seed" in n for n in notes), notes


def test_one_seed_in_a_head_ct_roots_the_tree_at_its_carotids_lower_end():
    vol, arteries, *_ = H.head_phantom("hu", 0.7)
    r = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=[H.SEED_LPS_MM])
    t = r.vessels.tree
    root = t.points_lps_mm[t.root]
    ica = H.dense_polyline(arteries["ICA_L"])[:, :3]
    d = np.linalg.norm(ica - root, axis=1)
    # on the seeded carotid's axis, at its lower end (the first 5 % of it), below the seed
    assert d.min() < t.radius_mm[t.root] + 0.5 and np.argmin(d) < 0.05 * len(ica), (root, d.min(), np.argmin(d))
    assert root[2] < H.SEED_LPS_MM[2] - 20.0
