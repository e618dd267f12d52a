"""The CTA (or any angiographic volume): volume -> vessel mask -> centerline tree with radii (stage 1 of DESIGN.md).

- ``grid``: the voxel grid helpers the stages share (index -> LPS, checks, bounding boxes, finite differences)
- ``segment``: the vessel mask of a CTA in HU (HU window, multi-scale vesselness, the tubular component)
- ``surface``: the surface mesh of the mask
- ``centerline``: the centerline graph of the mask (distance-transform ridges, skeleton graph, radii)
- ``vessels3d``: the three chained (``extract_vessels``), with stage timings
- ``vesselmodel``: the intensity model taken from the volume itself (HU CTA, MRA, 3DRA) and the plausibility checks
- ``lostlumen``: the segmented lumen no ball of the tree covers (two vessels fused in the mask, the tree kept one)
- ``biasfield``: an MR angiogram's intensity bias field (N4), divided out when the automatic stage refuses a volume not in
  HU, or its tissue level varies like a field's
- ``prune``: a tree without its wide branches whose axis is dim (unenhanced veins, marrow), when only they make it implausible
"""
