"""The CTA (or any angiographic volume): volume -> vessel mask -> centerline tree with radii (stage 1 of DESIGN.md).

- ``vessels3d``: the vessel mask and the centerline graph of a CTA in HU
- ``vesselmodel``: the intensity model taken from the volume itself (HU CTA, MRA, 3DRA) and the plausibility checks
"""
