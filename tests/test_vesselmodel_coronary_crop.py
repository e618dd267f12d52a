"""A coronary CTA (a crop around the heart) fully automatic (``scripts/bench_coronary_cta.py``, stop 44).

Its chambers' contrast blood is 13 % of the body, whose spread (about 200 HU) put the vessels' candidate threshold
at 653 HU, above a CTA's contrast: no contrast lumen was a candidate, bone was read as a 3DRA's contrast and the
volume refused "only 44% of the voxels at the lumen level 890.7 (in HU, brighter than a CTA's contrast: a 3DRA's
contrast, or a CT's bone) are tubular". Still refused (no automatic coronary tree yet), but for its real reason and
with the seed that helps.
"""
from __future__ import annotations

import pytest

from guidewire3d.cta import vesselmodel
from guidewire3d.errors import SegmentationError

from test_bench_coronary_phantom import B  # the benchmark module, loaded once


@pytest.fixture(scope="module")
def coronary_ct():
    vol, tree, _ = B.coronary_phantom(spacing_mm=0.8, slice_mm=1.0, seed=0)  # coarser than the benchmark: 6 s
    return vol, tree


def test_a_coronary_cta_is_refused_naming_its_blood_pools_not_a_3dra(coronary_ct):
    vol, _ = coronary_ct
    with pytest.raises(SegmentationError) as e:
        vesselmodel.extract_vessels_auto(vol)
    msg = str(e.value)
    assert "crop around the heart" in msg and "aortic root or a coronary artery" in msg and "\n" not in msg
    assert "3DRA" not in msg
