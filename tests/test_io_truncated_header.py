"""A DICOM file cut anywhere in its header is named truncated (a one-line error), wherever the cut falls.

``tests/test_bad_inputs.py`` cuts the simulator's roadmap at 300 bytes. Whether that lands between two elements of
the file meta group (pydicom then reads a dataset without PixelData) or inside one (pydicom raises
``struct.error``) depends on the lengths of its UIDs, which vary from file to file: the error named the file as
"truncated" in the first case only, and the test failed now and then.
"""
from __future__ import annotations

from pathlib import Path

import pytest

from guidewire3d import io
from guidewire3d.errors import Guidewire3DError


@pytest.mark.parametrize("example", ["ct", "rgb_color"])
def test_every_cut_in_the_header_is_named_truncated(tmp_path, example):
    from pydicom import examples

    data = Path(examples.get_path(example)).read_bytes()
    f = tmp_path / "cut.dcm"
    cuts = range(140, min(len(data) // 2, 2000), 3)       # after the preamble and the 'DICM' marker
    for n in cuts:
        f.write_bytes(data[:n])
        with pytest.raises(Guidewire3DError) as e:
            io._read_dicom_header(f, "a DICOM image")
        msg = str(e.value)
        assert str(f) in msg and "truncated" in msg and "\n" not in msg, (n, msg)
