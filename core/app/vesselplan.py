"""``guidewire3d vessels``: the vessel tree of a CTA, MRA or 3DRA alone, for planning (issue 17).

Reads the volume, runs :func:`guidewire3d.cta.vesselmodel.extract_vessels_auto` and writes an output
folder that appears only when complete (a staging folder renamed at the end, as ``reconstruct``
does): ``centerline.vtp``, ``vessels.stl``, ``vessels.vtp`` and ``vessels.json``.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.app import export
from guidewire3d.cta import lostlumen, vesselmodel
from guidewire3d.vesseltree import access_record, check_access, rooted_at_access

__all__ = ["vessels_record", "run_to_outdir", "cli_main"]

MIN_FREE_MB = 16


def vessels_record(auto, *, inputs: dict, access_lps_mm=None) -> dict:
    """The content of ``vessels.json``: inputs, the intensity model, the plausibility record, the
    branches (parent, length, radii, end points) and stage timings; with ``access_lps_mm`` (the tree
    rooted at it) also ``"access"`` (:func:`guidewire3d.vesseltree.access_record`)."""
    tree = auto.vessels.tree
    P, R = tree.points_lps_mm, tree.radius_mm
    branches = []
    for b in tree.branches:
        ids = b.point_ids
        seg = np.linalg.norm(np.diff(P[ids], axis=0), axis=1)
        branches.append({
            "index": int(b.index),
            "parent": int(b.parent),
            "children": [int(c) for c in b.children],
            "n_points": int(len(ids)),
            "length_mm": round(float(seg.sum()), 2),
            "radius_mm": {"min": round(float(R[ids].min()), 2), "median": round(float(np.median(R[ids])), 2),
                          "max": round(float(R[ids].max()), 2)},
            "start_lps_mm": [round(float(v), 2) for v in P[ids[0]]],
            "end_lps_mm": [round(float(v), 2) for v in P[ids[-1]]],
        })
    rec = {
        "inputs": inputs,
        "intensity_model": auto.model.to_dict(),
        "plausibility": auto.plausibility.to_dict(),
        "segmentation": {"pass": auto.segmentation, "first_pass_problems": list(auto.first_pass_problems),
                         "pruned": auto.pruned, "seeded": auto.seeded, "bias_field": auto.bias_field},
        "tree": {
            "n_points": int(tree.n_points),
            "n_branches": len(tree.branches),
            "total_length_mm": round(float(tree.total_length_mm), 1),
            "root_lps_mm": [round(float(v), 2) for v in P[tree.root]],
            "radius_mm": {"min": round(float(R.min()), 2), "median": round(float(np.median(R)), 2),
                          "max": round(float(R.max()), 2)},
            "vessel_volume_cm3": round(auto.plausibility.vessel_cm3, 2),
            # how far the centerline may lie from the vessels' axes (1 sigma per axis, from the voxel spacing)
            "centerline_sigma_mm": (None if tree.centerline_sigma_mm is None
                                    else round(float(tree.centerline_sigma_mm), 3)),
            # segmented lumen no ball of the tree covers (two vessels fused in the mask, the tree kept one): a wire
            # projecting onto it may run there (cta.lostlumen)
            "lost_lumen_mm3": (None if tree.lost_lumen_lps_mm is None
                               else round(lostlumen.lost_lumen_mm3(tree, inputs["spacing_mm"]), 1)),
        },
        "branches": branches,
        "timing": {k: round(float(v), 3) for k, v in auto.seconds.items()},
    }
    if access_lps_mm is not None:
        rec["access"] = access_record(tree, access_lps_mm)
    return rec


def run_to_outdir(cta, out_dir, *, seeds_lps_mm=None, series_uid=None, progress: bool = True, access_lps_mm=None,
                  log=None):
    """Read ``cta``, extract its vessels and write ``out_dir`` atomically; returns the ``AutoVessels``.

    Every check that can be made before the work is made first (the output location, the
    volume, its geometry, the seeds, the access point); a volume without a plausible vessel tree
    raises and leaves nothing behind. ``access_lps_mm`` (LPS mm, optional): where the wire will enter;
    the tree written (and returned) is rooted at its point nearest to it
    (:func:`guidewire3d.vesseltree.rooted_at_access`).
    """
    out_dir = Path(out_dir)
    io.require_empty_folder(out_dir, min_free_mb=MIN_FREE_MB)
    t0 = time.perf_counter()
    vol = io.read_volume(cta, series_uid=series_uid, log=log, modalities=("CT", "MR"))
    vesselmodel.check_geometry(vol)
    seeds = None if not seeds_lps_mm else np.asarray(seeds_lps_mm, dtype=float).reshape(-1, 3)
    if access_lps_mm is not None:
        access_lps_mm = check_access(access_lps_mm, bounds_lps_mm=vol.bounds_lps_mm)
    t_load = time.perf_counter() - t0
    with io.staged_folder(out_dir) as staging:
        auto = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seeds, progress=progress)
        auto = dataclasses.replace(auto, vessels=lostlumen.with_lost_lumen(vol, auto.vessels))
        auto.seconds["load"] = t_load
        if access_lps_mm is not None:
            tree = rooted_at_access(auto.vessels.tree, access_lps_mm)
            auto = dataclasses.replace(auto, vessels=dataclasses.replace(auto.vessels, tree=tree))
        inputs = {"cta": str(Path(cta).resolve()), "series_uid": vol.series_uid,
                  "shape_zyx": list(vol.shape_zyx), "spacing_mm": list(vol.spacing_mm),
                  "seeds_lps_mm": None if seeds is None else seeds.round(3).tolist()}
        if access_lps_mm is not None:
            inputs["access_lps_mm"] = [round(float(v), 3) for v in access_lps_mm]

        def write(staging: Path) -> None:
            export.write_polydata(auto.vessels.tree.to_polydata(), staging / "centerline.vtp")
            export.write_polydata(auto.vessels.surface, staging / "vessels.stl")
            export.write_polydata(auto.vessels.surface, staging / "vessels.vtp")
            rec = vessels_record(auto, inputs=inputs, access_lps_mm=access_lps_mm)
            io.atomic_write_text(staging / "vessels.json", json.dumps(rec, indent=1))

        io.write_into(out_dir, staging, write)
    return auto


def cli_main(args) -> int:
    def say(msg):
        print(msg, file=sys.stderr)

    auto = run_to_outdir(args.cta, args.out, seeds_lps_mm=args.seed_lps, series_uid=args.series_uid, log=say,
                         progress=sys.stderr.isatty(), access_lps_mm=getattr(args, "access_lps", None))
    m, t = auto.model, auto.vessels.tree
    if auto.first_pass_problems:
        how = "the strict pass's tree" if auto.segmentation.startswith("strict") else "the tree"
        cut = f", {auto.pruned}" if auto.pruned else ""
        say(f"note: the first vessel tree was implausible ({'; '.join(auto.first_pass_problems)}); {how} is "
            f"written{cut} (check it in the viewer)")
    elif auto.pruned:  # blood pools cut, or one of two separate structures chosen, from a tree that passed
        say(f"note: {auto.pruned} (check it in the viewer)")
    if auto.bias_field:
        say(f"note: {auto.bias_field}; the tree is that of the corrected volume (the intensity levels in vessels.json "
            f"are its)")
    if auto.seeded == "automatic tree":
        say("the automatic vessel tree holds every seed: it is written, rooted at its end nearest the first seed")
    elif auto.seeded == "seeds":
        say("the automatic vessel tree does not hold every seed: the tree is the seeds' own, from the lumen level read "
            "at them")
    access = getattr(args, "access_lps", None)
    if access is not None:
        rec = access_record(t, access)
        say(f"the tree is rooted at {rec['root_lps_mm']}, its point nearest --access-lps ({rec['distance_mm']:.1f} mm "
            "from it)")
    print(f"wrote {args.out}: {len(t.branches)} branches, {t.total_length_mm / 10:.1f} cm of centerline, "
          f"radius {np.median(t.radius_mm):.1f} mm median / {t.radius_mm.max():.1f} mm max, "
          f"{auto.plausibility.vessel_cm3:.1f} cm3; lumen {m.lumen:.4g}, background {m.background:.4g} "
          f"({'HU' if m.hu else 'arbitrary units'}, {m.source}); {auto.seconds.get('total', 0.0):.1f} s")
    return 0
