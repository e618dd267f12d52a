"""Diagnostic experiment behind the real-anatomy README paragraph (issue 17): what the registration
does on ``bench_real_anatomy.py``'s poses if (a) the roadmap's field-of-view rule took only dark regions
touching an image side over >= 20 % of it for collimator shutters (``imaging.field_of_view`` takes every
region darker than a quarter of the median, the aorta of a dense aortogram included), and/or (b) the
global search's in-plane shift range were 150 mm instead of ``search.SEARCH_SHIFT_MM`` (40 mm).

Both are monkeypatched here, in this process only: neither is in the product. Per pose it prints
``fov/shift/start: verdict mTRE`` (start ``nom``: nominal, ``vc``: isocentre at the in-view tree
points' centroid) and the LM minimum from the true pose (``lm_true``).

    nice .venv/bin/python scripts/diagnose_real_anatomy.py 6
"""
import sys
import warnings
from pathlib import Path

import numpy as np
warnings.filterwarnings("ignore")
sys.path.insert(0, str(Path(__file__).parent))

import real_anatomy as ra, bench_real_anatomy as b
from guidewire3d import metrics, registration
from guidewire3d.geometry import nominal_pose
from guidewire3d.xray import roadmap as rm, imaging
from guidewire3d.registration import search
from scipy import ndimage as ndi
cache = Path.home() / ".cache" / "guidewire3d"
vol, labels, ref_mm, ref_lab = ra.load_case(cache)
tree = b.cached_tree(vol, cache, print)["tree"]
wires = b.cached_wires(vol, labels, cache)
iod = ra.iodine_fraction(vol, labels); mu = ra.anatomy_mu(vol, labels)
orig_fov = imaging.field_of_view
def fov_border(im01, margin_px):
    """dark = outside the collimator only for dark components touching a side over >= 20 % of it"""
    sm = ndi.uniform_filter(im01, size=2 * margin_px + 1)
    med = float(np.median(sm))
    dark = sm <= imaging.FOV_DARK_FRACTION * med if med > 0 else np.zeros_like(sm, bool)
    lab, n = ndi.label(dark)
    keep = np.zeros(n + 1, bool)
    H, W = dark.shape
    for side, L in ((lab[0], W), (lab[-1], W), (lab[:, 0], H), (lab[:, -1], H)):
        c = np.bincount(side, minlength=n + 1); c[0] = 0
        keep |= c >= 0.2 * L
    fov = ~keep[lab]
    fov = ndi.binary_erosion(fov, iterations=margin_px, border_value=1)
    bb = imaging.BORDER_PX
    fov[:bb] = fov[-bb:] = False; fov[:, :bb] = fov[:, -bb:] = False
    return fov
rng = np.random.default_rng(0)
P = tree.points_lps_mm
for k in range(int(sys.argv[1])):
    target, carm, pose = b.make_pose(rng, k, wires)
    road, frames, tw, L = b.render(rng, carm, pose, wires[target], iod, mu, vol)
    inv = carm.in_image(carm.project(P, pose)); Pv = P[inv]
    mr = float(tree.radius_mm.max()) / carm.pixel_at_iso_mm * 1.5
    out = [k]
    for fovname, f in (("orig", orig_fov), ("border", fov_border)):
        rm.field_of_view = f
        cl = rm.roadmap_centerline(road, max_radius_px=mr)
        uv = np.asarray(cl.points_uv_px)
        for shift in (40.0, 150.0):
            search.SEARCH_SHIFT_MM = shift
            for sname, st in (("nom", None), ("vc", nominal_pose(Pv.mean(0)))):
                r = registration.register(tree, uv, carm, init_pose=st, centerline_radius_px=cl.radius_px)
                out.append(f"{fovname}/{shift:.0f}/{sname}: {'ok' if r.success else 'no'} {metrics.mtre_mm(r.pose, pose, Pv):.1f}")
        search.SEARCH_SHIFT_MM = 40.0
        out.append(f"{fovname}/lm_true {metrics.mtre_mm(registration.refine(tree, uv, carm, pose, centerline_radius_px=cl.radius_px).pose, pose, Pv):.1f}")
    print(" | ".join(map(str, out)), flush=True)
