"""Per-pose diagnosis of registration on ``bench_real_anatomy.py``'s poses (issue 17), registration only.

The benchmark's inputs (the same poses, roadmaps and 2D centerlines: the same ``--seed``, ``make_pose``,
``render`` and ``roadmap_centerline`` calls) are prepared once and cached (``--cache``; rendering the live
frames, which the random stream needs, costs ~1 min per pose); then every run registers them in seconds.
Per pose and per start (``nom``: ``register`` from the nominal start as the product; ``true``: ``refine`` from
the true pose, i.e. where the energy's minimum near the truth is), it prints the verdict, the check that
refused it (``bench_real_anatomy.refusal``), mTRE over the tree's in-view points, the narrow-stage energy (the
true start's lower than the nominal's = the global search missed the right basin), residual, inliers, pose
1-sigma / limit, the explained fraction and the jackknife 1-sigma.

    nice .venv/bin/python scripts/diagnose_real_anatomy.py --poses 20 [--set NAME=VALUE ...] [--tree seeded]

``--set`` patches a registration module constant (as ``bench_registration.py --set``) in this process only.
``--tree seeded``: the tree of ``bench_real_anatomy.py --seed-aorta`` (the planning workflow's seed).
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_real_anatomy as b  # noqa: E402
import real_anatomy as ra  # noqa: E402


def prepared_cases(n: int, seed: int, cache: Path, log):
    """The benchmark's registration inputs for poses ``0..n-1`` of ``seed``, cached (one file per seed)."""
    from guidewire3d.xray.roadmap import roadmap_centerline

    f = cache / "real_anatomy" / f"diagnose_cases_seed{seed}_{b._cta_digest()}.pkl"
    have = pickle.loads(f.read_bytes()) if f.is_file() else []
    if len(have) >= n:
        return have[:n]
    vol, labels, _, _ = ra.load_case(cache)
    tree = b.cached_tree(vol, cache, log)["tree"]
    wires = b.cached_wires(vol, labels, cache)
    iodine, mu_ct = ra.iodine_fraction(vol, labels), ra.anatomy_mu(vol, labels)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t0 = time.perf_counter()
        target, carm, pose = b.make_pose(rng, k, wires)
        roadmap, _, _, _ = b.render(rng, carm, pose, wires[target], iodine, mu_ct, vol)  # draws as the benchmark
        if k < len(have):
            out.append(have[k])
            continue
        cl = roadmap_centerline(roadmap, max_radius_px=float(tree.radius_mm.max()) / carm.pixel_at_iso_mm * 1.5)
        out.append(dict(k=k, target=target, carm=carm, pose=pose, uv=np.asarray(cl.points_uv_px, float),
                        radius=np.asarray(cl.radius_px, float)))
        log(f"pose {k}: prepared in {time.perf_counter() - t0:.0f} s")
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(pickle.dumps(out))
    return out


def main(argv=None):
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "guidewire3d"))
    ap.add_argument("--tree", choices=("auto", "seeded"), default="auto")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    a = ap.parse_args(argv)
    from guidewire3d import metrics, registration
    from guidewire3d.registration import problem, search, solve, verdict

    for kv in a.set:
        name, value = kv.split("=", 1)
        mod = next((m for m in (verdict, search, solve, problem) if hasattr(m, name)), None)
        if mod is None:
            ap.error(f"--set: no registration module has a constant {name}")
        kind = type(getattr(mod, name))
        setattr(mod, name, value.lower() in ("1", "true", "yes") if kind is bool else kind(value))

    def log(m):
        print(m, file=sys.stderr, flush=True)

    cache = Path(a.cache).expanduser()
    cases = prepared_cases(a.poses, a.seed, cache, log)
    vol, labels, _, _ = ra.load_case(cache) if a.tree == "seeded" else (None,) * 4
    if a.tree == "seeded":
        W = b.cached_wires(vol, labels, cache)[58]
        seeds = W[np.searchsorted(b._arclength(W), 0.25 * b._arclength(W)[-1])][None]
        tree = b.cached_tree(vol, cache, log, seeds)["tree"]
    else:
        tree = b.cached_tree(None, cache, log)["tree"] if _tree_cached(cache) else None
        if tree is None:
            vol, labels, _, _ = ra.load_case(cache)
            tree = b.cached_tree(vol, cache, log)["tree"]
    P = tree.points_lps_mm
    print(f"load {os.getloadavg()[0]:.1f}; tree {a.tree}: {len(P)} points, {tree.total_length_mm / 1000:.2f} m; "
          f"set: {' '.join(a.set) or '-'}")
    print("| pose | start | verdict | refused by | mTRE view mm | energy | residual px | inliers | 1-sigma / limit mm "
          "| explained (in view) | jackknife mm |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    n_ok = n_right = n_wrong = n_near = 0
    for c in cases:
        carm, pose = c["carm"], c["pose"]
        Pv = P[carm.in_image(carm.project(P, pose))]
        r = registration.register(tree, c["uv"], carm, centerline_radius_px=c["radius"])
        rt = registration.refine(tree, c["uv"], carm, pose, centerline_radius_px=c["radius"])
        for name, rr in (("nom", r), ("true", rt)):
            m = metrics.mtre_mm(rr.pose, pose, Pv)
            print(f"| {c['k']} | {name} | {rr.verdict.label} | {b.refusal(rr)} | {m:.1f} | {rr.energy:.0f} | "
                  f"{rr.mean_residual_px:.2f} | {rr.inlier_fraction:.2f} | "
                  f"{rr.pose_std_mm:.2f} / {rr.max_pose_std_mm:.2f} | "
                  f"{rr.explained_fraction:.2f} | {rr.jackknife_std_mm:.2f} |", flush=True)
        m = metrics.mtre_mm(r.pose, pose, Pv)
        n_ok += bool(r.success and m < b.SUCCESS_MM)
        n_wrong += bool(r.success and m >= b.SUCCESS_MM)
        n_right += bool(not r.success and m < b.SUCCESS_MM)
        n_near += bool(m < b.SUCCESS_MM)
    n = len(cases)
    print(f"\nfrom the nominal start: success {n_ok}/{n}, ok but wrong {n_wrong}, refused but right {n_right}, "
          f"within {b.SUCCESS_MM:g} mm {n_near}/{n}")


def _tree_cached(cache: Path) -> bool:
    return (cache / "real_anatomy" / f"tree_{b._cta_digest()}.pkl").is_file()


if __name__ == "__main__":
    main()
