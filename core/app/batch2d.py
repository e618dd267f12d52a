"""2D analysis of image files from the command line (``guidewire3d segment``).

Reads angiograms and live frames -- XA / RF DICOM files (single- or multi-frame; no C-arm
geometry needed), PNG / TIFF / JPEG images, or folders of them -- and writes, per image, the
vessel mask (:func:`guidewire3d.xray.roadmap.vessel_mask`), the guidewire mask
(:func:`guidewire3d.xray.segmentation.guidewire_mask`) and the ordered wire
(:func:`guidewire3d.xray.orderedwire.ordered_wire`, proximal -> distal) into a new folder:

- ``<name>_vessels.png`` and ``<name>_wire.png``: masks, 0 / 255 (8-bit grey);
- ``<name>_overlay.png``: the image with the vessel skeleton (green) and the ordered wire (yellow),
  for a quick look;
- ``segment.json``: the options and, per image, its source, frame, shape, the vessel-mask
  fraction and the ordered wire (``success``, ``message``, ``length_px``, ``points_uv_px``, and
  ``presence``: the evidence of :func:`guidewire3d.xray.wirepresence.wire_presence`; a frame without a
  wire has ``success: false`` and ``message`` "no guidewire in the frame: <why>"; ``beyond_tip``: a
  piece of the wire mask beyond the traced tip and in line with it, so the tip is not settled, or null;
  ``doubled_tip``: the traced tip is about twice as dark as the wire, two layers of wire (it may bend
  back over itself before its tip: :func:`guidewire3d.xray.orderedwire.doubled_tip`), or null;
  ``hairpin_px``: the stretch the wire runs back along itself where a hairpin whose limbs merge in the
  mask was followed round, px, 0 when none was).

``<name>`` is the file's stem, with ``_fNNNN`` for the frames of a multi-frame file. Every input
is read and checked before anything is computed, and the folder appears only when complete.
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from guidewire3d import io
from guidewire3d.app.export import overlay_image, write_png
from guidewire3d.errors import InputError
from guidewire3d.methods import SegMethod, choices
from guidewire3d.xray.orderedwire import doubled_tip, ordered_wire
from guidewire3d.xray.roadmap import vessel_mask
from guidewire3d.xray.imaging import as_image
from guidewire3d.xray.segmentation import guidewire_mask
from guidewire3d.xray.wiremask import projected_wire_radius_px

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
WHAT_CHOICES = ("both", "vessels", "wire")


@dataclass(frozen=True, eq=False)
class InputImage:
    """One 2D image to analyse: ``name`` (output prefix), ``source`` path, ``frame`` index in a
    multi-frame file (None for a single image), the pixels, and the C-arm view if the file had one."""

    name: str
    source: str
    frame: int | None
    image: np.ndarray
    carm: object | None = None


def _is_dicom(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(132)
    return len(head) == 132 and head[128:132] == b"DICM"


def _read_dicom(path: Path) -> list[InputImage]:
    frames, carm = io.read_xa_frames(path)
    if len(frames) == 1:
        return [InputImage(path.stem, str(path), None, frames[0], carm)]
    return [InputImage(f"{path.stem}_f{k:04d}", str(path), k, f, carm) for k, f in enumerate(frames)]


def _read_picture(path: Path) -> InputImage:
    im = None
    if path.suffix.lower() in (".tif", ".tiff"):
        # OpenCV reads compressed TIFF (LZW, deflate: what cv2.imwrite writes) without imagecodecs
        import cv2

        im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if im is not None and im.ndim == 3:
            im = cv2.cvtColor(im, cv2.COLOR_BGRA2RGBA if im.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    if im is None:
        from skimage.io import imread

        try:
            im = imread(path)
        except Exception as e:  # noqa: BLE001
            raise InputError(f"{path}: unreadable image ({e.__class__.__name__}: {str(e)[:100]})") from None
    return InputImage(path.stem, str(path), None, as_image(im, str(path)))


def read_inputs(paths) -> list[InputImage]:
    """The images of the given files and folders (folders: their image and DICOM files, sorted
    by name), in order.

    Raises
    ------
    InputError, DicomError
        A path that does not exist, an empty folder, an unreadable file, or two images with the
        same output name.
    """
    images: list[InputImage] = []
    for p in map(Path, paths):
        if p.is_symlink() and not p.exists():
            raise InputError(f"{p}: dangling symbolic link (its target does not exist)")
        if not p.exists():
            raise InputError(f"{p}: no such file or folder")
        if not p.is_dir() and not p.is_file():
            raise InputError(f"{p}: not a regular file or a folder (a pipe, socket or device)")
        if p.is_file() and p.stat().st_size == 0:
            raise InputError(f"{p}: empty file (0 bytes)")
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.is_file() and not f.name.startswith("."))
            files = [f for f in files if f.suffix.lower() in IMAGE_SUFFIXES or _is_dicom(f)]
            if not files:
                raise InputError(f"{p}: no DICOM or PNG/TIFF/JPEG images in the folder")
        else:
            files = [p]
        for f in files:
            if _is_dicom(f) or f.suffix.lower() == ".dcm":
                images.extend(_read_dicom(f))
            elif f.suffix.lower() in IMAGE_SUFFIXES:
                images.append(_read_picture(f))
            else:
                raise InputError(f"{f}: not a DICOM file or a PNG/TIFF/JPEG image")
    names = [im.name for im in images]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"two inputs give the same output name {dup[0]!r}: rename one")
    return images


def analyse(image: InputImage, *, what: str = "both", segmenter: str = "unet", wire_model: bool = False,
            wire_diameter_mm: float | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """The record (for ``segment.json``) and the masks (``{"vessels": ..., "wire": ...}``) of one image."""
    rec = {"name": image.name, "source": image.source, "frame": image.frame, "shape": list(image.image.shape)}
    masks = {}
    if what in ("both", "vessels"):
        masks["vessels"] = vessel_mask(image.image)
        rec["vessel_fraction"] = round(float(masks["vessels"].mean()), 6)
    if what in ("both", "wire"):
        radius = None
        if wire_diameter_mm is not None:
            radius = projected_wire_radius_px(image.carm, wire_diameter_mm)
        m = guidewire_mask(image.image, method=segmenter, wire_model=wire_model, wire_radius_px=radius)
        masks["wire"] = m
        ow = ordered_wire(m, image=image.image)
        rec["wire"] = {
            "success": bool(ow),
            "message": ow.message,
            "length_px": round(float(ow.length_px), 3) if ow else 0.0,
            "points_uv_px": np.round(np.asarray(ow), 3).tolist() if ow else [],
            # issue #20: is the traced curve a guidewire (False: "no guidewire in the frame: <why>")
            "presence": ow.presence.as_dict() if ow.presence is not None else None,
            # a piece of the mask beyond the tip, in line with the wire: the tip is not settled
            "beyond_tip": None if ow.beyond_tip is None else {
                "length_px": round(ow.beyond_tip.length_px, 1), "gap_px": round(ow.beyond_tip.gap_px, 1),
                "angle_deg": round(ow.beyond_tip.angle_deg, 1), "message": ow.beyond_tip.explain()},
            # a hairpin whose limbs merge in the mask, followed round (orderedwire.HAIRPIN_*)
            "hairpin_px": round(float(ow.hairpin_px), 1),
        }
        # two layers of wire at the traced tip (the wire bends back over itself before it): not settled
        doubled = doubled_tip(np.asarray(image.image), np.asarray(ow)) if ow and np.ndim(image.image) == 2 else None
        rec["wire"]["doubled_tip"] = None if doubled is None else {
            "darkness_ratio": round(doubled.darkness_ratio, 2), "message": doubled.explain()}
    return rec, masks


def overlay(image: np.ndarray, record: dict, masks: dict[str, np.ndarray]) -> np.ndarray:
    """RGB picture of one result: the vessel mask's skeleton (green), the ordered wire (yellow)."""
    from skimage.morphology import skeletonize

    skeleton_uv = None
    if "vessels" in masks:
        rows, cols = np.nonzero(skeletonize(masks["vessels"]))
        skeleton_uv = np.column_stack([cols, rows]).astype(float)
    wire = record.get("wire", {})
    wire_uv = np.asarray(wire["points_uv_px"], float) if wire.get("success") else None
    return overlay_image(image, centerline_uv_px=skeleton_uv, wire2d_uv_px=wire_uv, text=record["name"])


def cli_segment(args) -> int:
    """``guidewire3d segment``: analyse the inputs, write the masks and ``segment.json``."""
    from tqdm import tqdm

    out_dir = io.require_empty_folder(args.out)
    if args.wire_diameter_mm is not None and not args.wire_model:
        raise InputError("--wire-diameter-mm: only used with --wire-model")
    images = read_inputs(args.inputs)
    if args.wire_diameter_mm is not None:
        missing = next((im for im in images if im.carm is None), None)
        if missing is not None:
            raise InputError(f"{missing.source}: --wire-diameter-mm needs the C-arm geometry tags of a DICOM XA file")
    records, all_masks = [], []
    for im in tqdm(images, desc="segment", file=sys.stderr, disable=len(images) < 2):
        rec, masks = analyse(im, what=args.what, segmenter=args.segmenter, wire_model=args.wire_model,
                             wire_diameter_mm=args.wire_diameter_mm)
        records.append(rec)
        all_masks.append(masks)
    summary = {
        "version": 1,
        "inputs": [str(Path(p).resolve()) for p in args.inputs],
        "options": {"what": args.what, "segmenter": args.segmenter, "wire_model": bool(args.wire_model),
                    "wire_diameter_mm": args.wire_diameter_mm},
        "images": records,
    }

    def write(staging: Path) -> None:
        for im, rec, masks in zip(images, records, all_masks):
            for kind, m in masks.items():
                write_png(staging / f"{rec['name']}_{kind}.png", np.where(m, 255, 0).astype(np.uint8))
            write_png(staging / f"{rec['name']}_overlay.png", overlay(im.image, rec, masks))
        io.atomic_write_text(staging / "segment.json", json.dumps(summary, indent=1))

    io.write_folder_atomically(out_dir, write)  # refuses an out_dir filled meanwhile
    n_wire = sum(1 for r in records if r.get("wire", {}).get("success"))
    n_absent = sum(1 for r in records if (r.get("wire", {}).get("presence") or {}).get("present") is False)
    wire_part = (f"; ordered wire found in {n_wire}/{len(records)}" + (f" (no guidewire in {n_absent})" if n_absent else "")
                 if args.what != "vessels" else "")
    print(f"wrote {out_dir}: {len(records)} image(s){wire_part}")
    return 0


def add_cli_options(p) -> None:
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="XA/RF DICOM file (single- or multi-frame), PNG/TIFF/JPEG image, or a folder of them")
    p.add_argument("--out", required=True, help="output folder (created; must be empty or absent)")
    p.add_argument("--what", default="both", choices=WHAT_CHOICES,
                   help="vessel masks, guidewire masks with the ordered wire, or both (default)")
    p.add_argument("--segmenter", default=SegMethod.UNET.value, choices=choices(SegMethod),
                   help="guidewire segmentation: unet (default) or ridge (classical)")
    p.add_argument("--wire-model", action="store_true",
                   help="render the guidewire mask from the traced wire (sharper edges on thin wires)")
    p.add_argument("--wire-diameter-mm", type=float, default=None, metavar="D",
                   help="with --wire-model: the wire's diameter (0.36 for 0.014\"), projected with the DICOM "
                        "geometry; default: the radius is estimated from the mask")


__all__ = ["InputImage", "read_inputs", "analyse", "cli_segment", "add_cli_options"]
