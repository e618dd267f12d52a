"""The CTA vessel stage's compiled kernels (``kernels._compile_cta``) against what they replaced:
SciPy's exact distance transform (ball dilation, depth test), skan's ``Skeleton`` (paths, lengths,
pruning) and the first compiled Frangi kernel."""
import numpy as np
import pytest
from guidewire3d import kernels
from guidewire3d.cta import segment
from guidewire3d.cta.centerline import _SkeletonPaths
from guidewire3d.cta.grid import edt_mm
from scipy import ndimage as ndi

SPACINGS = [np.array([2.5, 0.703125, 0.703125]), np.array([0.5, 0.5, 0.5]), np.array([1.0, 0.8, 0.6])]


def _blobs(rng, shape, p, grow):
    m = rng.random(shape) < p
    return ndi.binary_dilation(m, iterations=grow) if grow else m


@pytest.mark.parametrize("k_sp", range(len(SPACINGS)))
def test_dilate_ball_equals_distance_transform(k_sp):
    sp = SPACINGS[k_sp]
    rng = np.random.default_rng(k_sp)
    for trial in range(4):
        m = _blobs(rng, (30, 41, 37), 0.003 * (trial + 1), trial % 3)
        m[0, 5, 5] = m[-1, -1, -1] = True  # on the array's border
        ref_d = ndi.distance_transform_edt(~m, sampling=sp)
        for r in (0.5, 1.6, 3.0, 3.64, 6.5, 11.7):
            got = kernels.dilate_ball(m, r, sp)
            assert np.array_equal(got, ref_d <= r), (trial, r)


def test_dilate_ball_empty_and_ball_offsets():
    sp = np.array([2.0, 1.0, 1.0])
    assert not kernels.dilate_ball(np.zeros((5, 6, 7), bool), 3.0, sp).any()
    off = kernels.ball_offsets(2.0, sp)
    assert len(off) == len({tuple(o) for o in off})
    assert np.all(np.sqrt(((off * sp) ** 2).sum(axis=1)) <= 2.0)
    # every offset of the enclosing box within the radius is there
    g = np.argwhere(np.ones((3, 5, 5), bool)) - [1, 2, 2]
    assert len(off) == int(np.sum(np.sqrt(((g * sp) ** 2).sum(axis=1)) <= 2.0))


@pytest.mark.parametrize("k_sp", range(len(SPACINGS)))
def test_deeper_than_equals_distance_transform(k_sp):
    # spacings exact in binary: with 0.6 / 0.8 / 1.0 mm a distance of 3 mm is reached along two axes
    # (5 x 0.6, 3 x 1.0) whose float32 roundings differ, and which one the transform meets first
    # depends on its box
    sp = [np.array([2.5, 0.703125, 0.703125]), np.array([0.5, 0.5, 0.5]), np.array([1.25, 0.75, 0.5])][k_sp]
    rng = np.random.default_rng(10 + k_sp)
    zz, yy, xx = np.mgrid[:40, :60, :60]
    for trial in range(3):
        c = rng.uniform([10, 15, 15], [30, 45, 45])
        r = rng.uniform(6.0, 14.0)
        ball = ((zz - c[0]) * sp[0]) ** 2 + ((yy - c[1]) * sp[1]) ** 2 + ((xx - c[2]) * sp[2]) ** 2 <= r * r
        m = ball | _blobs(rng, ball.shape, 0.002, 2)
        if trial == 2:
            m[:3] = True  # a slab touching the border: the transform ignores what lies beyond it
        ref = edt_mm(m, sp)  # what segment_vessels computed before
        for depth in (1.0, 3.0, 0.6 * r, r - 1.0):
            got = segment._deeper_than(m, depth, sp)
            assert np.array_equal(got, ref > depth), (trial, depth)
    assert not segment._deeper_than(np.zeros((8, 8, 8), bool), 1.0, sp).any()


def _tree_skeleton(rng, shape=(24, 40, 40)):
    """A voxel skeleton with junctions, spurs and a loop: thinned random tubes."""
    from skimage.morphology import skeletonize

    m = np.zeros(shape, bool)
    for _ in range(6):
        a, b = rng.uniform(2, np.array(shape) - 3, size=(2, 3))
        for t in np.linspace(0, 1, 80):
            p = np.round(a + t * (b - a)).astype(int)
            m[p[0] - 1:p[0] + 2, p[1] - 1:p[1] + 2, p[2] - 1:p[2] + 2] = True
    return skeletonize(m).astype(bool)


def test_skeleton_paths_equal_skan():
    from skan import Skeleton

    sp = np.array([2.5, 0.7, 0.7])
    for seed in range(4):
        skel = _tree_skeleton(np.random.default_rng(seed))
        ref = Skeleton(skel, spacing=tuple(sp))
        got = _SkeletonPaths.of(skel, sp)
        assert ref.n_paths == got.n_paths > 3
        assert np.array_equal(ref.degrees, got.degrees)
        assert np.array_equal(ref.coordinates, got.coordinates)
        assert np.array_equal(ref.path_lengths(), got.lengths)
        for k in range(ref.n_paths):
            assert np.array_equal(ref.path(k), got.path(k))
        # pruning the terminal paths: the same image as skan's prune_paths
        deg = got.degrees
        term = [k for k in range(got.n_paths) if (deg[got.path(k)[[0, -1]]] == 1).sum() == 1][:3]
        pr = ref.prune_paths(term)
        img = np.zeros(skel.shape, bool)
        img[tuple(np.round(pr.coordinates).astype(int).T)] = True
        assert np.array_equal(got.pruned(skel, term), img)
        # Lee's thinning is idempotent (the centerline thins a pruned skeleton once, not twice)
        from skimage.morphology import skeletonize

        assert np.array_equal(skeletonize(img).astype(bool), img)


def test_frangi_at_threads_same_values():
    rng = np.random.default_rng(4)
    F = ndi.gaussian_filter(rng.random((40, 60, 60)), 1.5).astype(np.float32)
    idx = np.argwhere(np.ones((38, 58, 58), bool)) + 1
    sp = np.array([2.5, 0.7, 0.7])
    one = kernels.frangi_at(F, idx, sp, 1.6, alpha=0.5, beta=0.5, gamma=0.15)
    two = kernels.frangi_at(F, idx, sp, 1.6, alpha=0.5, beta=0.5, gamma=0.15, threads=2)
    assert len(idx) > 2 * 50_000 and (one > 0).mean() > 0.05
    assert np.array_equal(one, two)
