"""The controls of scripts/diagnose_real_anatomy.py (issue 17) against hand-built ground truth: the label oracle
removes exactly the branches in non-arterial labels and what hangs beyond them, the 2D controls keep or move the
points they say, and the depth shift is the translation along the beam."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

HEART, AORTA, LUNG = 51, 52, 10
STEP_MM = 1.0


def _y_tree_and_labels(root_in_heart: bool):
    """A tree on a 1 mm grid: a trunk from (10, 30, 30) to (30, 30, 30) (index x, y, z), an artery from its end to
    (50, 30, 30), a heart branch from its end to (30, 50, 30) that forks into a lung twig to (30, 50, 45) and a
    twig in the aorta label to (45, 50, 30) (not in a non-arterial label, but beyond the heart branch); the trunk
    is aorta, or heart with ``root_in_heart`` (then a wide heart pool at the root: the tree's widest end)."""
    from guidewire3d import io
    from guidewire3d.vesseltree import VesselTree

    n = 64
    labels = np.zeros((n, n, n), np.int16)
    vol = io.Volume(np.zeros((n, n, n), np.float32), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), source="y-tree")
    pts, rad, par = [], [], []

    def path(a, b, parent, label, r):
        a, b = np.asarray(a, float), np.asarray(b, float)
        k = int(round(np.linalg.norm(b - a) / STEP_MM))
        prev = parent
        for t in np.linspace(0, 1, k + 1)[1:] if parent >= 0 else np.linspace(0, 1, k + 1):
            p = a + t * (b - a)
            pts.append(p)
            rad.append(r)
            par.append(prev)
            prev = len(pts) - 1
            x, y, z = np.rint(p).astype(int)
            labels[z, y, x] = label
        return prev

    trunk_end = path((10, 30, 30), (30, 30, 30), -1, HEART if root_in_heart else AORTA, 9.0 if root_in_heart else 6.0)
    art_end = path((30, 30, 30), (50, 30, 30), trunk_end, AORTA, 5.0)
    heart_end = path((30, 30, 30), (30, 50, 30), trunk_end, HEART, 4.0)
    path((30, 50, 30), (30, 50, 45), heart_end, LUNG, 2.0)
    path((30, 50, 30), (45, 50, 30), heart_end, AORTA, 2.0)
    tree = VesselTree(np.asarray(pts), np.asarray(rad), np.asarray(par))
    return tree, vol, labels, art_end


def test_label_oracle_cuts_heart_branch_and_what_lies_beyond():
    import diagnose_real_anatomy as d

    tree, vol, labels, art_end = _y_tree_and_labels(root_in_heart=False)
    out = d.without_labelled_branches(tree, vol, labels)
    P = out.points_lps_mm
    # kept: the trunk and the artery (x from 10 to 50 at y = 30), nothing at y > 30 (heart branch, lung twig)
    assert np.all(np.abs(P[:, 1] - 30.0) < 1e-9)
    assert P[:, 0].min() == 10.0 and P[:, 0].max() == 50.0
    assert abs(out.total_length_mm - 40.0) < 1e-6


def test_label_oracle_reroots_when_the_root_is_in_the_heart():
    import diagnose_real_anatomy as d

    tree, vol, labels, art_end = _y_tree_and_labels(root_in_heart=True)
    # the trunk (heart, with the root and the junction point) and everything beyond it from the artery's end, the
    # new root (the widest end outside the removed branches), go: the artery's own points stay
    out = d.without_labelled_branches(tree, vol, labels)
    P = out.points_lps_mm
    assert np.all(np.abs(P[:, 1] - 30.0) < 1e-9)
    assert sorted(np.rint(P[:, 0]).astype(int).tolist()) == list(range(31, 51))
    assert np.allclose(P[out.root], (50.0, 30.0, 30.0))


def _carm_case():
    from guidewire3d.geometry import CArm, Pose

    carm = CArm(10.0, 5.0, 1000.0, 700.0, 0.3, (256, 256))
    line = np.column_stack([np.linspace(-20, 20, 81), np.zeros(81), np.zeros(81)])
    pose = Pose.identity()
    uv = carm.project(line, pose)
    return carm, pose, line, uv


def test_controlled_uv_on_ref_and_snapped():
    import diagnose_real_anatomy as d

    carm, pose, line, uv_true = _carm_case()
    rng = np.random.default_rng(0)
    off = np.zeros_like(uv_true)
    off[:, 1] = rng.uniform(-0.8, 0.8, len(uv_true))  # sub-pixel offsets across the line
    far = np.array([[uv_true[40, 0], uv_true[40, 1] + 10.0]])  # a point 10 px off the reference
    c = dict(carm=carm, pose=pose, uv=np.vstack([uv_true + off, far]), radius=np.ones(len(uv_true) + 1))
    uv, rad = d.controlled_uv(c, "roadmap", line, line)
    assert len(uv) == len(uv_true) + 1
    uv, rad = d.controlled_uv(c, "on-ref", line, line)
    assert len(uv) == len(uv_true) == len(rad)
    np.testing.assert_allclose(uv, uv_true + off)
    uv, _ = d.controlled_uv(c, "snapped", line, line)
    assert np.max(np.linalg.norm(uv - uv_true, axis=1)) < 0.1  # onto the projected line (0.5 mm samples)


def test_depth_shift_is_the_translation_along_the_beam():
    import diagnose_real_anatomy as d
    from guidewire3d.geometry import Pose

    carm, pose, line, _ = _carm_case()
    beam = carm.axes[2]  # camera z in the room frame
    moved = Pose(np.eye(3), 5.0 * beam) @ pose
    assert abs(d.depth_shift_mm(carm, pose, moved, line) - 5.0) < 1e-9
    side = Pose(np.eye(3), 5.0 * carm.axes[0]) @ pose
    assert abs(d.depth_shift_mm(carm, pose, side, line)) < 1e-9


def test_smooth_offsets_have_the_asked_rms_and_correlation():
    import diagnose_real_anatomy as d

    uv = np.column_stack([np.linspace(0, 4000, 4001), np.zeros(4001)])
    rms = []
    for seed in range(40):
        f = d.smooth_offsets_px(uv, 0.5, 40.0, np.random.default_rng(seed))
        rms.append(np.sqrt(np.mean(f ** 2, axis=0)))
        # neighbours 1 px apart move together (correlated)
        near = np.corrcoef(f[:-1, 0], f[1:, 0])[0, 1]
        assert near > 0.99
    assert abs(float(np.mean(rms)) - 0.5) < 0.1
