"""export.overlay_image: centerline pixels at the image border."""
import numpy as np

from guidewire3d.app.export import overlay_image


def test_centerline_points_rounding_onto_the_border_are_dropped():
    frame = np.full((8, 6), 100.0)
    # u = 5.7 and v = 7.6 lie inside the image's extent but round to column 6 / row 8 (out of range);
    # (2.2, 3.4) is drawn at row 3, column 2; a negative one rounding to 0 is drawn too
    uv = np.array([[5.7, 1.0], [1.0, 7.6], [2.2, 3.4], [-0.4, 0.2], [np.nan, 1.0]])
    rgb = overlay_image(frame, centerline_uv_px=uv)
    green = np.argwhere((rgb == (0, 200, 0)).all(-1))
    assert sorted(map(tuple, green)) == [(0, 0), (3, 2)]
