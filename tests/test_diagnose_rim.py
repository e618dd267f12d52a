"""The roadmap's iodine rim (issue 17, the toward-source depth bias): the benchmark's one-voxel partial-volume rim of
the artery labels also takes the voxels of a bone label the artery touches (bone is above 100 HU), which shifts the
vessel's iodine centre toward the bone; the control ``iodine_fraction_unlabelled_rim`` keeps the rim in unlabelled
voxels only, and its centre stays on the artery's axis. Hand-built volume, ground truth: the axis."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

AORTA, RIB = 52, 92
AXIS_YX = (20.0, 20.0)  # the artery's axis (index y, x) on every slice
R_VOX = 4.0


def _artery_beside_a_rib(rim_hu: float):
    """A straight artery along z (label AORTA, 400 HU, radius R_VOX voxels about AXIS_YX), a partial-volume rim
    of ``rim_hu`` around it in unlabelled voxels, and a rib (label RIB, 900 HU) hugging the artery's +x half (in place of the rim there)."""
    from guidewire3d import io

    n = 40
    zz, yy, xx = np.mgrid[0:8, 0:n, 0:n]
    r = np.hypot(yy - AXIS_YX[0], xx - AXIS_YX[1])
    labels = np.zeros((8, n, n), np.int16)
    hu = np.zeros((8, n, n), np.float32)
    labels[r <= R_VOX] = AORTA
    hu[r <= R_VOX] = 400.0
    hu[(r > R_VOX) & (r <= R_VOX + 1.5)] = rim_hu
    rib = (xx > AXIS_YX[1] + 1.0) & (r > R_VOX) & (r <= R_VOX + 3.0)  # hugs the artery's +x half
    labels[rib] = RIB
    hu[rib] = 900.0
    vol = io.Volume(hu, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), source="artery-rib")
    return vol, labels


def _centre_x(frac_zyx, offset_zyx):
    f = frac_zyx.sum(axis=(0, 1))
    x = np.arange(len(f)) + offset_zyx[2]
    return float((f * x).sum() / f.sum())


def test_unlabelled_rim_keeps_bone_out_and_the_iodine_centre_on_the_axis():
    import diagnose_real_anatomy as d

    # no partial volume outside the label: the lumen is the label, its axis the ground truth
    vol, labels = _artery_beside_a_rib(rim_hu=0.0)
    ctrl = d.iodine_fraction_unlabelled_rim(vol, labels)
    assert abs(_centre_x(*ctrl) - AXIS_YX[1]) < 1e-6
    # the control keeps the unlabelled partial-volume rim: (250 - 100) / (400 - 100) = 0.5, and no rib voxel
    from scipy import ndimage as ndi

    vol, labels = _artery_beside_a_rib(rim_hu=250.0)
    f = _full(*d.iodine_fraction_unlabelled_rim(vol, labels), labels.shape)
    art = labels == AORTA
    ring = ndi.binary_dilation(art, iterations=1) & ~art & (labels == 0)
    assert ring.any() and np.allclose(f[ring], 0.5)
    assert np.all(f[labels == RIB] == 0.0) and np.allclose(f[art], 1.0)


def test_phantom_iodine_has_no_bone_and_its_centre_on_the_axis():
    """The phantom's roadmap iodine (``phantom.realct.iodine_fraction_zyx``) keeps the rib's voxels out of the
    artery's partial-volume rim (stop 36; before, a one-sided fringe that biased the registered depth)."""
    import real_anatomy as ra

    vol, labels = _artery_beside_a_rib(rim_hu=0.0)
    bench = ra.iodine_fraction(vol, labels)
    f = _full(*bench, labels.shape)
    assert np.all(f[labels == RIB] == 0.0)
    assert abs(_centre_x(*bench) - AXIS_YX[1]) < 1e-6


def _full(frac_zyx, lo, shape):
    f = np.zeros(shape, np.float32)
    f[lo[0]:lo[0] + frac_zyx.shape[0], lo[1]:lo[1] + frac_zyx.shape[1], lo[2]:lo[2] + frac_zyx.shape[2]] = frac_zyx
    return f
