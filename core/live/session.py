"""The per-frame engine: one live frame in; its 2D wire, 3D wire and verdict out.

Every front end runs its frames through :class:`Session`: ``reconstruct`` (``pipeline.run``),
the viewer's *apply*, the Slicer logic and, for streaming, ``guidewire3d live``. A frame's path:

1. guidewire mask (``segmentation.GuidewireSegmenter``, ROI tracking between frames);
2. ordered 2D wire (``orderedwire.ordered_wire``, proximal end nearest the projected tree root);
3. 3D wire inside the vessel tree (``reconstruction.WireTracker``: the previous frame's path is a
   prior, a failed frame does not replace it);
4. the frame's verdict: ``ok``, ``uncertain`` (a 3D wire exists but something about it is not
   settled: which end is the tip, whether the wire goes on beyond its tip through a stretch the
   segmenter lost or bends back over itself before it (two layers of wire at the traced tip),
   where the tip is (``TIP_MAX_UNCERTAINTY_MM``; ``TIP_STRETCH_MAX_MM``: its vessel runs along the
   beam, and a tip right in 2D may lie mm off in 3D), or whether it is in view at all) or ``failed``,
   with the reason.

Which end is the tip rests on two independent cues. In 2D, the proximal end is the one nearer the
projected root of the vessel tree (``hint_margin``: how much nearer, relative). In 3D, a wire
advanced from the root runs away from it through the tree (``Wire3D.tree_rise_mm``). When both
speak and disagree (for example the proximal part of the wire runs beyond the segmented tree and
projects over other branches), the frame is ``uncertain`` and says so; it is never silently
reported with the tip at the wrong end. A frame whose processing raises is reported as failed
with the error, and the session goes on.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
from guidewire3d import kernels, reconstruction
from guidewire3d.errors import Guidewire3DError
from guidewire3d.live.continuation import wire_continuation
from guidewire3d.live.tipslide import forward_stretch_mm, tip_slide_mm
from guidewire3d.geometry import CArm, Pose, fine_pixel_factor
from guidewire3d.motion.tracking import MotionTracker
from guidewire3d.registration import Verdict
from guidewire3d.vesseltree import VesselTree
from guidewire3d.xray import segmentation
from guidewire3d.xray.orderedwire import OrderedWire, ordered_wire, tip_end_check
from guidewire3d.xray.wirepresence import catheter_end

__all__ = ["Orientation", "FrameResult", "Session", "orientation_of", "frame_verdict", "tip_stretch_mm",
           "wire_uncertainty_mm"]

log = logging.getLogger(__name__)

#: the 2D cue speaks when the proximal end is nearer the projected root than the distal end by at
#: least this fraction of their summed distances ((d_far - d_near) / (d_far + d_near))
HINT_MARGIN_MIN = 0.15
#: without the 3D cue, the 2D cue alone decides only when it is this strong (on simulated wires
#: whose proximal part runs beyond the segmented tree, the root's projection put the true tip
#: first with margins up to 0.28)
HINT_MARGIN_ALONE = 0.5
#: the 3D cue speaks when the path through the tree rises (or falls) by at least this much (mm);
#: the same as ``ReconOptions.reverse_mm``, the reconstruction's own reversal trigger
TREE_RISE_MIN_MM = 5.0
#: a tip whose own uncertainty (``Wire3D.uncertainty_mm[-1]``, 1 sigma) is larger than this is not
#: reported ``ok``: it was placed beyond the end of the vessel tree's path by extrapolation, or
#: another branch explains the wire's distal part about as well (on simulated frames with the
#: true tree, correct tips stay below 2 mm). An ``ok`` frame promises its tip within 5 mm, about 2.2 x this.
#: It was 3 mm until stop 50: of the ``ok`` frames with a tip 1 sigma of 2.25-3 mm, 3 of 6 were more than
#: 5 mm off (``bench_stress`` 7808 f4, 2.95 mm, 5.8 mm off; 8509 f4, 2.41 mm, 5.75 mm off; one simulated
#: frame at the true pose), against 0 of the 4 at 2-2.25 mm and 10 of 591 (other causes) below 1.5 mm.
#: Since stop 51 the tip's uncertainty *along* its vessel counts too (``frame_verdict``'s ``tip_slide_mm``): the
#: stretch of vessel through whose lumen the 2D tip's ray passes (``live.tipslide``), any point of which
#: projects onto the tip, as a uniform spread (its length / sqrt 12), added in quadrature
TIP_MAX_UNCERTAINTY_MM = 2.25
#: a path through the vessel tree that walks back towards the root by more than this (mm) along the
#: wire (``Wire3D.tree_retreat_mm``) does not follow the wire: the 2D trace took the wrong way at a
#: crossing (on simulated frames with the true tree, right paths stay below 3 mm)
TREE_RETREAT_MAX_MM = 6.0
#: a path through another branch (``Wire3D.branch_extra_cost``: its extra cost, in the Viterbi's
#: units of 2 x log-likelihood) below this, whose end lies more than ``BRANCH_SHIFT_MIN_MM`` from
#: the chosen end, makes the branch ambiguous. The shift is the tip accuracy a frame reported ``ok``
#: promises (``scripts/bench_stress.py --tip-mm``, 5 mm): at 10 mm, frames with an equally good path
#: ending 6-9 mm away were ``ok`` with their tips 5.4-7.6 mm off (true pose, seeds 0-179, 4 frames:
#: 2 of 601 right-end ``ok`` frames, and ``bench_stress`` seed 3910 frame 0); at 5 mm 8 of the 601, whose
#: tips were right, become ``uncertain`` as well
BRANCH_EXTRA_MAX = 4.0
BRANCH_SHIFT_MIN_MM = 5.0
#: a path through the vessel tree that reaches the tip's vessel by a skip (``Wire3D.tip_skip_px``,
#: ``reconstruction.path.tip_skip_px``): a step within ``path.TIP_SKIP_NEAR_PX`` of the tip whose projected tree route
#: covers more than this many px (at ``geometry.REFERENCE_PIXEL_AT_ISO_MM``) beyond the wire's own step. The path
#: then puts the tip in a vessel that the wire's last anchors project onto, entered through tree the wire does not
#: follow: ``bench_stress`` 7207 f3 (31 px, the tip 7.1 mm off in a side branch; its best rival path 4.35 above
#: the branch check's limit) and 7223 f3 (43 px: a 2D trace that crossed between the limbs of a hairpin, the tip
#: 17.7 mm off), both ``ok`` before. Four anchor steps (``ReconOptions.dp_step_px``, 5 px): a path that follows
#: the wire stays within a few px (the pairwise cost's ``sigma_step_px``, 3 px). Right paths also skip, where the
#: tree's junction lies off the wire's turn or the 2D wire bridges a gap straight across a bend, by as much as
#: wrong ones (22-46 px): the check costs right tips. Measured: on the simulator at the true pose (seeds 0-149, 4
#: frames) 4 of 475 right ``ok`` frames become ``uncertain`` and none of the 6 wrong ones is caught; on
#: ``bench_stress`` 7200-7223 the 2 wrong ``ok`` frames and 4 of 76 right ones; 7100-7115, 7600-7615 and the
#: wide 7700-7711 none; held out, 7800-7815: 1 of 43 right ones (7805 f2, its tip 4.2 mm off) and no wrong one;
#: and in ``tests/test_live_continuation_offlumen.py``'s breathing sequence 3 of its 6 right ``ok`` frames (skips of
#: 20.3, 23.1 and 74.6 px with the tips 0.3-0.6 mm off). The skip does not separate right tips from wrong ones, so it
#: is measured and reported (``Wire3D.tip_skip_px`` in the frame record), not gated: off (infinite) by default
TIP_SKIP_MAX_PX = float("inf")
#: a wire whose rays pass more than this (mm, at the vessel) outside the lumen of the tree path they were
#: placed in (``Wire3D.lumen_miss_mm``) is not in that vessel there: a frame reported ``ok`` promises a wire
#: within 2 mm (``bench_stress`` / ``bench_motion``'s ``WIRE_OFF_MM``), and a reconstruction whose own points lie
#: further outside their vessel than that contradicts its prior (the wire is in the lumen). It happens when
#: the tree lacks the vessel the wire is in (a real CTA tree drawn through a rib where the subclavian artery
#: crosses it: the tip 10.4 mm off, ``ok``) or the pose is off there (the static roadmap pose under breathing:
#: ``bench_motion --only sim``, 34 of its 56 silently wrong ``ok`` frames, 1 of its 146 right ones; with the
#: pose tracked 1 of 4 wrong, seed 19 f0 with its tip 28 mm off, and none of the 427 right ones)
OFF_LUMEN_MAX_MM = 2.0
#: a wire of which more than this (mm) also projects onto segmented lumen the vessel tree does not follow, 2-20 mm
#: from it (``Wire3D.lost_lumen_stretch_mm``, ``cta.lostlumen``: two vessels fused in the CTA's mask, the tree kept
#: one) may run in that lost vessel, at another depth: ``bench_stress`` 7105 f1, the true vessel's first 13 mm
#: fused with its neighbour, the wire placed in the neighbour 5.9 mm off along the beam over 25 mm, ``ok`` before
LOST_LUMEN_STRETCH_MAX_MM = 5.0
#: the words that name that reason in a verdict's message
LOST_LUMEN_WORDS = "segmented vessel lumen that the CTA's centerline tree does not follow"
#: a wire whose own points are known to worse than this (``Wire3D.uncertainty_mm``, the median over its points of
#: ``sqrt(trace Sigma)``, an rms 3D error) is not reported ``ok``: an ok frame promises a wire within 2 mm
#: (``OFF_LUMEN_MAX_MM``, ``bench_stress``'s ``WIRE_OFF_MM``), and one view does not fix the wire's depth inside a
#: lumen much wider than that. On the real-anatomy frames (``scripts/diagnose_real_frames.py --root entry``, the
#: true pose) the 18 ``ok`` frames of a transfemoral wire in the aorta had 11 whose wire was 2.05-3.44 mm off, all
#: with a median 1 sigma of 2.2-3.1 mm; the 7 within 2 mm had 1.3-2.5 mm
WIRE_MAX_UNCERTAINTY_MM = 2.0
#: the tip along the beam: the 3D wire's arclength over the last ``TIP_STRETCH_PX`` px of its 2D wire
#: (``tip_stretch_mm``). Where the tip's vessel runs in the image plane, they span about 5 x the
#: pixel size at the isocentre (about 1 mm); where it turns along the beam, many mm project onto
#: those few px, and a 2D tip right to a pixel or two (the trace's end cap, the lumen's width, a pose
#: a little off) leaves the 3D tip mm off along the vessel: ``bench_stress`` 3504 f3 (9.8 mm over
#: the last 5 px, the tip 12.1 mm off) and 3505 f1 (6.0 mm, 7.1 mm off), both reported ``ok`` before.
#: Above ``TIP_STRETCH_MAX_MM`` the tip is not settled (on simulated frames at the true pose and on
#: the stress cases, ok frames with the tip right stayed below 4 mm). In px at
#: ``geometry.REFERENCE_PIXEL_AT_ISO_MM`` (0.8 mm at the isocentre); a finer view measures over as many mm
#: (``fine_pixel_factor``: 10 px at 0.08 mm), else the same 3D stretch would lie over half the mm there
TIP_STRETCH_PX = 5.0
TIP_STRETCH_MAX_MM = 4.5
#: a 2D wire whose distal end is this close to the image border (px) runs out of the view there:
#: its tip is not seen (it may re-enter the image elsewhere)
TIP_BORDER_PX = 1.5
#: the ROI-tracked mask is doubted, and the frame segmented again full-frame
#: (``GuidewireSegmenter.segment_again``), when the wire traced in it is shorter than the previous frame's
#: by more than ``max(TRACKED_SHRINK_MIN_PX, TRACKED_SHRINK_FRACTION x`` that length), or is not found at all.
#: The network run on small boxes can lose a faint stretch inside a box that the full frame shows, the wire then
#: in two pieces too far apart to join: ``bench_stress`` 8112 f4 (a 0.25 mm wire moving 10 mm), 311 px of a
#: 508 px wire traced, the tip 27 mm off, ``ok``. A wire pulled back at 50 mm/s retracts about 12 px a frame
#: at 15 frames/s; the full frame then confirms the shorter wire at the cost of one more network pass
TRACKED_SHRINK_MIN_PX = 24.0
TRACKED_SHRINK_FRACTION = 0.1
#: ... and the tracked pass is run again, looking around the new tip too, when the traced tip moved more than this
#: from the previous frame's (px): the first pass looked ``segmentation.LOOK_AHEAD_PX`` (32 px) around the old tip
#: only, and a wire that advanced further may go on beyond a gap there (``bench_stress`` 8318 f1: the wire crossing
#: its own proximal part 38 px beyond the last tip, the trace stopped at the crossing, the tip 8 mm off, ``ok``)
LOOK_AGAIN_PX = 16.0


@dataclass(frozen=True, eq=False)
class Orientation:
    """Which end of a frame's wire is the tip, and how sure that is.

    Attributes
    ----------
    hint_margin : float
        ``(d_far - d_near) / (d_far + d_near)`` of the output's ends to the projected tree root:
        positive when the output's first point is the end nearer the root (NaN without a root).
    tree_rise_mm : float
        Arclength from the tree root gained along the output's path through the tree (NaN when
        the method does not use the tree).
    reversed_by_tree : bool
        The reconstruction reversed the 2D order because the tree explained the wire better so.
    cue_2d, cue_3d : int
        +1: the cue agrees with the output's order; -1: it says the output runs tip -> proximal;
        0: the cue does not speak.
    """

    hint_margin: float
    tree_rise_mm: float
    reversed_by_tree: bool
    cue_2d: int
    cue_3d: int

    @property
    def conflict(self) -> bool:
        """The cues disagree, or the tree reversed the 2D order against the 2D position of the root."""
        return self.cue_2d * self.cue_3d < 0 or (self.reversed_by_tree and self.hint_margin < 0)

    @property
    def determined(self) -> bool:
        """The tree's path rises towards the tip with no 2D cue against it, or, where the tree is
        silent, the 2D cue is strong (``HINT_MARGIN_ALONE``)."""
        if self.conflict:
            return False
        if self.cue_3d > 0:
            return True
        return self.cue_3d == 0 and np.isfinite(self.hint_margin) and self.hint_margin >= HINT_MARGIN_ALONE

    @property
    def confidence(self) -> str:
        """``high`` (both cues agree), ``medium`` (one agrees, the other is silent), ``low``."""
        if self.cue_2d > 0 and self.cue_3d > 0:
            return "high"
        return "medium" if self.determined else "low"

    def explain(self) -> str:
        if self.conflict:
            near = "the wire's first point" if self.hint_margin > 0 else "the wire's last point"
            return (f"tip end uncertain: in 2D {near} is nearer the vessel tree's root, but the path through the tree "
                    f"{'rises' if self.tree_rise_mm > 0 else 'falls'} {abs(self.tree_rise_mm):.0f} mm from the "
                    f"first point to the tip" + (" (the tree reversed the 2D order)" if self.reversed_by_tree else ""))
        if not self.determined:
            if self.cue_3d < 0:
                return (f"tip end uncertain: the path through the tree falls {abs(self.tree_rise_mm):.0f} mm towards "
                        f"the tip, and the 2D position of the tree root does not decide it")
            return ("tip end uncertain: the path through the tree does not rise towards either end, and the 2D "
                    "position of the tree root does not decide it clearly")
        return ""

    def to_dict(self) -> dict:
        def f(x):
            return None if not np.isfinite(x) else round(float(x), 4)

        return {"confidence": self.confidence, "conflict": bool(self.conflict), "hint_margin": f(self.hint_margin),
                "tree_rise_mm": f(self.tree_rise_mm), "reversed_by_tree": bool(self.reversed_by_tree),
                "cue_2d": int(self.cue_2d), "cue_3d": int(self.cue_3d)}


def orientation_of(wire3d, wire_uv_px, *, root_uv_px=None) -> Orientation:
    """The :class:`Orientation` of a reconstructed wire.

    Parameters
    ----------
    wire3d : reconstruction.Wire3D
        A successful reconstruction (``reversed_input``, ``tree_rise_mm`` are read).
    wire_uv_px : (M, 2) ndarray of float
        The 2D wire as it was given to the reconstruction (proximal -> distal as ordered in 2D).
    root_uv_px : (2,) array_like, optional
        The projected vessel-tree root in the frame (the 2D cue); without it the 2D cue is silent.
    """
    uv = np.asarray(wire_uv_px, float).reshape(-1, 2)
    rev = bool(getattr(wire3d, "reversed_input", False))
    margin = float("nan")
    cue_2d = 0
    if root_uv_px is not None and len(uv) >= 2:
        h = np.asarray(root_uv_px, float).reshape(2)
        first, last = (uv[-1], uv[0]) if rev else (uv[0], uv[-1])
        d_first, d_last = float(np.linalg.norm(first - h)), float(np.linalg.norm(last - h))
        margin = (d_last - d_first) / max(d_last + d_first, 1e-9)
        cue_2d = int(np.sign(margin)) if abs(margin) >= HINT_MARGIN_MIN else 0
    rise = float(getattr(wire3d, "tree_rise_mm", float("nan")))
    cue_3d = int(np.sign(rise)) if np.isfinite(rise) and abs(rise) >= TREE_RISE_MIN_MM else 0
    return Orientation(margin, rise, rev, cue_2d, cue_3d)


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One live frame's outcome (falsy when no 3D wire was made).

    ``verdict`` is ``registration.Verdict``: OK, UNCERTAIN (a 3D wire exists but ``message`` says
    what is not settled) or FAILED.
    """

    index: int
    wire2d: object  # orderedwire.OrderedWire (an (N, 2) array-like; falsy when not found)
    wire3d: object  # reconstruction.Wire3D
    verdict: object  # registration.Verdict
    message: str
    orientation: Orientation | None = None
    seconds: float = 0.0
    timestamp: float = field(default=float("nan"))  # the source frame's time stamp, when it has one
    pose: Pose | None = None  # the pose the frame was reconstructed in
    motion: object = None  # registration.RegistrationResult of the frame's pose update (track_motion), or None
    #: seconds per stage of this frame: "segmentation", "ordered_wire", "motion", "reconstruction"
    #: (those that ran; "reconstruction" includes the check of the image beyond the tip)
    stage_seconds: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.wire3d)

    @property
    def tip_lps_mm(self) -> np.ndarray:
        """The distal end ``(3,)``; NaNs when there is no 3D wire."""
        p = self.wire3d.points_lps_mm
        return p[-1].copy() if len(p) else np.full(3, np.nan)

    def to_dict(self) -> dict:
        d = {"index": int(self.index), "verdict": self.verdict.value, "verdict_message": self.message,
             "orientation": self.orientation.to_dict() if self.orientation is not None else None}
        if self.motion is not None:
            m = self.motion
            d["motion"] = {"pose": self.pose.matrix.tolist() if self.pose is not None else None,
                           "verdict": m.verdict.value, "message": m.message,
                           "residual_px": _finite_or_none(m.mean_residual_px),
                           "inlier_fraction": _finite_or_none(m.inlier_fraction)}
        return d


class Session:
    """The per-frame engine over one registration.

    Parameters
    ----------
    tree : VesselTree
        The CTA centerline tree (LPS mm).
    carm : CArm
        The live frames' view.
    pose : Pose
        ``T_iso_from_lps`` (the registration, or a user's correction).
    registration_covariance : (6, 6) ndarray, optional
        The pose covariance; it enters each point's uncertainty.
    segmenter : str, segmentation.SegMethod or a segmenter object
        ``"unet"`` (default) or ``"ridge"``: a ``segmentation.GuidewireSegmenter`` created on first
        use (a session fed 2D wires only, e.g. the viewer's *apply*, never loads a network); or an
        object with ``segment(frame) -> mask`` and ``reset()`` (one that also has
        ``segment(frame, look_uv=...)``, ``segment_again(frame, full=..., look_uv=...)`` and ``last_mode``,
        as ``GuidewireSegmenter`` has, gets its tracked masks doubted: :meth:`wire2d_of`).
    method : str or reconstruction.ReconMethod
        3D reconstruction method (default ``"vessel"``).
    track_motion : bool
        Follow breathing and heartbeat: each frame's 2D wire updates the pose
        (``motion.MotionTracker``, with the roadmap pose as its prior) before the frame is
        reconstructed in it, with the tracked pose's covariance in place of
        ``registration_covariance`` (the tracker's prior holds the latter). Off by default: with a
        static patient it only adds noise.
    """

    def __init__(self, tree: VesselTree, carm: CArm, pose: Pose, *, registration_covariance=None,
                 segmenter="unet", method="vessel", options=None, track_motion: bool = False,
                 motion_options=None):
        self.tree, self.carm = tree, carm
        self.method = getattr(method, "value", method)
        self.options = options
        if hasattr(segmenter, "segment"):  # a ready segmenter object (``segment(frame)``, ``reset()``)
            self.segmenter_method, self._segmenter = getattr(segmenter, "method", "custom"), segmenter
        else:
            self.segmenter_method, self._segmenter = getattr(segmenter, "value", segmenter), None
        self._reconstruction = reconstruction
        self.track_motion = bool(track_motion)
        self.motion_options = motion_options
        self.n_frames = 0
        self.n_segmented_again = 0      # frames whose tracked mask was doubted and segmented again (wire2d_of)
        self._last_wire_px = None       # the previous frame's traced 2D wire length
        self._last_tip_uv = None        # ... and its distal end, where the next tracked pass also looks
        self.tracker = None
        self._prior_was_ok = False  # the frame whose path is the tracker's prior was reported ok
        self.set_pose(pose, registration_covariance=registration_covariance)

    # --- state --------------------------------------------------------------------------------
    def set_pose(self, pose: Pose, *, registration_covariance=None) -> None:
        """Use ``pose`` (a new registration or a user's correction) from the next frame on: it is
        also the centre of the motion prior. The wire's temporal prior is kept."""
        self.motion_tracker = None
        if self.track_motion:
            self.motion_tracker = MotionTracker(self.tree, self.carm, pose, covariance=registration_covariance,
                                                options=self.motion_options)
        self._use_pose(pose, registration_covariance)

    def _use_pose(self, pose: Pose, registration_covariance) -> None:
        previous = self.tracker
        self.pose = pose
        self.registration_covariance = registration_covariance
        self.tracker = self._reconstruction.WireTracker(pose, self.carm, self.tree, method=self.method,
                                                        registration_covariance=registration_covariance,
                                                        options=self.options)
        if previous is not None:
            self.tracker.previous = previous.previous
        self.root_uv_px = self.carm.project(self.tree.points_lps_mm[self.tree.root], pose)

    @property
    def segmenter(self):
        if self._segmenter is None:
            self._segmenter = segmentation.GuidewireSegmenter(method=self.segmenter_method)
        return self._segmenter

    def reset(self) -> None:
        """Forget the previous frames (ROI tracking and the wire prior)."""
        if self._segmenter is not None:
            self._segmenter.reset()
        self.tracker.previous = None
        self._prior_was_ok = False
        self._last_wire_px = self._last_tip_uv = None
        if self.motion_tracker is not None:
            self.motion_tracker.reset()

    def warm_up(self, frame) -> None:
        """Load the network and run it once, and compile the kernels (first-call costs), without
        touching the tracking state."""
        kernels.warm_up()
        self.segmenter.segment(np.asarray(frame))
        self.segmenter.reset()

    # --- frames -------------------------------------------------------------------------------
    def process(self, frame, *, index: int | None = None, timestamp: float = float("nan")) -> FrameResult:
        """Segment, order and reconstruct one frame; never raises on a frame (a bad one is failed)."""
        t0 = time.perf_counter()
        index = self.n_frames if index is None else int(index)
        stages = {}
        try:
            img = np.asarray(frame)
            wire2d = self.wire2d_of(img, stages)
        except Guidewire3DError as e:
            return self._failed(index, None, f"bad frame: {e}", t0, timestamp)
        except Exception as e:  # noqa: BLE001 - a live session reports a broken frame and goes on
            log.exception("frame %d: 2D analysis raised", index)
            return self._failed(index, None, f"internal error in the 2D analysis: {e.__class__.__name__}: {e}",
                                t0, timestamp)
        return self._finish(index, wire2d, img, t0, timestamp, stages)

    def wire2d_of(self, img: np.ndarray, stages: dict | None = None) -> OrderedWire:
        """The frame's ordered 2D wire: the segmenter's mask (ROI-tracked between frames, looking also
        around the previous frame's tip), traced, its proximal end nearest the projected tree root.

        A tracked mask is doubted (``segmentation.GuidewireSegmenter.segment_again``):

        * when its wire is much shorter than the previous frame's, or not found (``TRACKED_SHRINK_*``):
          the frame is segmented again full-frame;
        * when its tip advanced more than ``LOOK_AGAIN_PX`` from the previous frame's: the tracked pass
          is run again, looking around the new tip too (the wire may go on beyond a gap there).

        Adds each stage's seconds to ``stages``."""
        stages = {} if stages is None else stages
        seg = self.segmenter
        redo = hasattr(seg, "segment_again")
        prev_px, prev_tip = self._last_wire_px, self._last_tip_uv
        look = [] if prev_tip is None or not redo else [prev_tip]
        seg_s = order_s = 0.0
        t0 = time.perf_counter()
        mask = seg.segment(img, look_uv=look) if look else seg.segment(img)
        t1 = time.perf_counter()
        wire2d = ordered_wire(mask, image=img, proximal_hint_uv=self.root_uv_px)
        seg_s, order_s = t1 - t0, time.perf_counter() - t1
        again = None
        if redo and prev_px is not None and getattr(seg, "last_mode", "") in ("roi", "roi-grown"):
            if not wire2d or wire2d.length_px < prev_px - max(TRACKED_SHRINK_MIN_PX, TRACKED_SHRINK_FRACTION * prev_px):
                again = {"full": True}
            elif np.linalg.norm(wire2d.tip_uv_px - prev_tip) > LOOK_AGAIN_PX:
                again = {"look_uv": look + [wire2d.tip_uv_px]}
        if again is not None:
            t0 = time.perf_counter()
            mask = seg.segment_again(img, **again)
            t1 = time.perf_counter()
            wire2d = ordered_wire(mask, image=img, proximal_hint_uv=self.root_uv_px)
            seg_s, order_s = seg_s + t1 - t0, order_s + time.perf_counter() - t1
            self.n_segmented_again += 1
        stages["segmentation"] = stages.get("segmentation", 0.0) + seg_s
        stages["ordered_wire"] = stages.get("ordered_wire", 0.0) + order_s
        self._last_wire_px = float(wire2d.length_px) if wire2d else None
        self._last_tip_uv = np.asarray(wire2d.tip_uv_px, float).copy() if wire2d else None
        return wire2d

    def process_wire(self, wire2d, *, image=None, index: int | None = None,
                     timestamp: float = float("nan")) -> FrameResult:
        """Reconstruct a frame from its ordered 2D wire (an ``OrderedWire`` or an (M, 2) px array)."""
        t0 = time.perf_counter()
        index = self.n_frames if index is None else int(index)
        return self._finish(index, wire2d, None if image is None else np.asarray(image), t0, timestamp)

    def _failed(self, index, wire2d, message, t0, timestamp, stages=None) -> FrameResult:
        self.n_frames += 1
        self.tracker.n_frames += 1
        self.tracker.failed_frames.append(index)
        w3 = self._reconstruction.Wire3D.failed(message, seconds=time.perf_counter() - t0, method=self.method)
        return FrameResult(index, wire2d if wire2d is not None else _no_wire(message), w3, Verdict.FAILED,
                           message, None, time.perf_counter() - t0, timestamp, self.pose,
                           stage_seconds=dict(stages or {}))

    def _finish(self, index, wire2d, image, t0, timestamp, stages=None) -> FrameResult:
        stages = {} if stages is None else stages
        has_flag = hasattr(wire2d, "success")
        if has_flag and not wire2d:
            return self._failed(index, wire2d, f"2D wire not found: {wire2d.message}", t0, timestamp, stages)
        uv = np.asarray(wire2d, float).reshape(-1, 2)
        if len(uv) < 2:
            return self._failed(index, wire2d, "2D wire not found: fewer than 2 points", t0, timestamp, stages)
        motion = None
        if self.motion_tracker is not None:
            t1 = time.perf_counter()
            motion = self.motion_tracker.update(uv)
            if not self.pose.allclose(motion.pose, atol_mm=1e-6, atol_rad=1e-9):
                self._use_pose(motion.pose, self.registration_covariance)
            # the tracked pose's own covariance (it holds the registration's) enters each point's uncertainty
            self.tracker.registration_covariance = motion.covariance_6x6
            stages["motion"] = time.perf_counter() - t1
        try:
            t1 = time.perf_counter()
            w3 = self.tracker.update(uv, image=image)
            stages["reconstruction"] = time.perf_counter() - t1
        except Guidewire3DError as e:
            return self._failed(index, wire2d, f"3D reconstruction refused the frame: {e}", t0, timestamp)
        except Exception as e:  # noqa: BLE001 - reported in the frame's record; the session goes on
            log.exception("frame %d: 3D reconstruction raised", index)
            return self._failed(index, wire2d, f"internal error in the 3D reconstruction: {e.__class__.__name__}: {e}",
                                t0, timestamp)
        self.n_frames += 1
        if not w3:
            return FrameResult(index, wire2d, w3, Verdict.FAILED, w3.message, None, time.perf_counter() - t0,
                               timestamp, self.pose, motion, stages)
        ori = orientation_of(w3, uv, root_uv_px=self.root_uv_px) if self.method == "vessel" else None
        continuation = None
        beyond_tip = getattr(wire2d, "beyond_tip", None)
        # the image beyond the tip is read only where frame_verdict would use it: not when a piece of
        # the mask beyond the tip already makes the tip uncertain
        # from the last wire point placed in a lumen: the tip itself may lie just outside its projected lumen
        # (its tree point is then -1, and before stop 33 the check measured nothing: seed 0 f16 of
        # ``bench_motion --only sim``, the wire doubled back into a branch, ``ok`` with the tip 14 mm off)
        on_tree = w3.tree_point_ids[w3.tree_point_ids >= 0]
        if (image is not None and self.method == "vessel" and len(on_tree)
                and (beyond_tip is None or w3.reversed_input)):
            t1 = time.perf_counter()
            continuation = wire_continuation(image, self.tree, self.carm, self.pose, int(on_tree[-1]),
                                             uv[::-1] if w3.reversed_input else uv)
            stages["reconstruction"] = stages.get("reconstruction", 0.0) + time.perf_counter() - t1
        slide_mm = forward_mm = None
        if self.method == "vessel" and len(on_tree):  # the lumen the tip's ray passes through, along the vessel
            t1 = time.perf_counter()
            slide_mm = tip_slide_mm(self.tree, self.carm, self.pose, uv[0] if w3.reversed_input else uv[-1],
                                    int(on_tree[-1]))
            forward_mm = forward_stretch_mm(self.tree, self.carm, self.pose, uv[0] if w3.reversed_input else uv[-1],
                                            int(on_tree[-1]), stretch_px=tip_stretch_px(self.carm.pixel_at_iso_mm))
            stages["reconstruction"] = stages.get("reconstruction", 0.0) + time.perf_counter() - t1
        cath = doubled = None
        if image is not None and image.ndim == 2:    # the image at the output's tip:
            t1 = time.perf_counter()
            # the trace ends on a catheter (the wire beyond it not seen)
            cath = catheter_end(image, uv, self.carm.pixel_at_iso_mm, at_end=not w3.reversed_input)
            # two layers of wire (a fold before the tip), or none (the trace runs past the wire's end)
            doubled = tip_end_check(image, uv, at_end=not w3.reversed_input)
            stages["reconstruction"] = stages.get("reconstruction", 0.0) + time.perf_counter() - t1
        verdict, message = frame_verdict(w3, uv, ori, beyond_tip=beyond_tip, doubled_tip=doubled,
                                         tip_fork=getattr(wire2d, "tip_fork", None),
                                         motion=motion, image_shape=self.carm.shape, continuation=continuation,
                                         prior_was_ok=self._prior_was_ok, pixel_at_iso_mm=self.carm.pixel_at_iso_mm,
                                         tip_slide_mm=slide_mm, catheter_end=cath, forward_mm=forward_mm)
        self._prior_was_ok = verdict is Verdict.OK      # the tracker's prior is now this frame's path
        return FrameResult(index, wire2d, w3, verdict, message, ori, time.perf_counter() - t0, timestamp,
                           self.pose, motion, stages)

    def run(self, frames, *, start_index: int = 0):
        """Yield a :class:`FrameResult` for each frame of an iterable, in order."""
        for k, frame in enumerate(frames):
            yield self.process(frame, index=start_index + k)


def frame_verdict(wire3d, wire_uv_px, orientation, *, beyond_tip=None, motion=None, image_shape=None,
                  continuation=None, doubled_tip=None, tip_fork=None, prior_was_ok: bool = False,
                  pixel_at_iso_mm: float | None = None, tip_slide_mm: float | None = None, catheter_end=None,
                  forward_mm: float | None = None):
    """``(Verdict, message)`` of a frame with a 3D wire: ``OK`` with the reconstruction's message,
    or ``UNCERTAIN`` with every reason that applies, the first first:

    * which end is the tip is not settled (``orientation``: :class:`Orientation`, or None);
    * a piece of the wire mask lies beyond the traced tip (``beyond_tip``: ``orderedwire.BeyondTip``);
    * the image shows a dark line going on along the vessel beyond the tip (``continuation``:
      :class:`guidewire3d.live.continuation.WireContinuation`);
    * the traced tip is about twice as dark as the wire: two layers of wire, the wire bends back
      over itself (or runs on under its own projection) before its true tip (``doubled_tip``:
      ``orderedwire.DoubledTip``, of the output's tip end); or barely darker than the background, the
      trace runs past the wire's end (``doubled_tip`` an ``orderedwire.BareTip``);
    * the traced end is as wide as a catheter (``catheter_end``: ``wirepresence.CatheterEnd``, wider than
      ``CATHETER_END_MIN_MM`` and ``CATHETER_END_MIN_PX``): the trace is the catheter's, the wire beyond it not seen;
    * the wire's mask forks just before the traced tip into a second end (``tip_fork``:
      ``orderedwire.TipFork``): a tip bent back, whose true end may be at the other branch;
    * the wire runs out of the image (``image_shape``, rows and cols) at its distal end;
    * the tip's vessel runs along the beam: the wire's last px span many mm in 3D
      (``TIP_STRETCH_MAX_MM``; over ``TIP_STRETCH_PX`` at the reference pixel, widened to as many mm on a
      view finer than that, ``pixel_at_iso_mm``; None: ``TIP_STRETCH_PX`` as it is);
    * the tip's uncertainty exceeds ``TIP_MAX_UNCERTAINTY_MM``: its 1 sigma across the wire
      (``Wire3D.uncertainty_mm[-1]``) and along it, the longer of ``tip_slide_mm`` and ``forward_mm`` over sqrt 12
      (``tip_slide_mm``: the stretch of vessel through whose lumen the 2D tip's ray passes,
      ``live.tipslide.tip_slide_mm``; ``forward_mm``: how much more of the vessel beyond the tip projects within
      ``TIP_STRETCH_PX`` of the 2D tip than across the beam, ``live.tipslide.forward_stretch_mm``, since stop 58; None:
      not measured),
      in quadrature;
    * the wire's points are known to worse than ``WIRE_MAX_UNCERTAINTY_MM`` (their median 1 sigma,
      ``wire_uncertainty_mm``): one view does not place a wire in depth inside a wide lumen;
    * the path through the tree walks back towards the root (``TREE_RETREAT_MAX_MM``);
    * a path through another branch explains the wire about as well (``BRANCH_EXTRA_MAX``), ending
      more than ``BRANCH_SHIFT_MIN_MM`` away: a branch the path entered avoided, the tip put in
      another vessel that projects onto the 2D tip, a path that ends at a leaf of the tree a few
      px before the tip, or a path that crosses into a vessel whose lumen touches the chosen route's
      where the tree joins the two elsewhere (``reconstruction.path.branch_alternative``,
      ``touching_rival``);
    * when gated (``TIP_SKIP_MAX_PX`` finite; off by default), the path reaches the tip's vessel by a skip: near the
      tip, the tree route of one step projects onto more than ``TIP_SKIP_MAX_PX`` beyond the wire's own step
      (``Wire3D.tip_skip_px``);
    * the wire's rays pass more than ``OFF_LUMEN_MAX_MM`` outside the lumen of the tree path they were
      placed in (``Wire3D.lumen_miss_mm``): the tree lacks the vessel the wire is in, or the pose is off;
    * more than ``LOST_LUMEN_STRETCH_MAX_MM`` of the wire also projects onto segmented lumen the tree does not
      follow (``Wire3D.lost_lumen_stretch_mm``): two vessels fused in the CTA, the wire may be in the lost one;
    * the frame's motion update did not fit (``motion``: its ``RegistrationResult``);
    * the wire left the path of the previous frame, which was reported ``ok`` (``prior_was_ok``): the
      reconstruction dropped that path as its prior (``Wire3D.prior_dropped``), the wire fitting another
      path through the tree much better. A wire advances and retracts along one path: one of the two
      frames, or the pose they were reconstructed in, is wrong (``bench_stress`` 6104 f2: the tracked pose
      drifting 5 mm off, the tip put 9.8 mm off in another branch, ``ok`` after an ``ok`` frame).
    """
    uv = np.asarray(wire_uv_px, float).reshape(-1, 2)
    reversed_ = bool(getattr(wire3d, "reversed_input", False))
    why = []
    if orientation is not None and (orientation.conflict or not orientation.determined):
        why.append(orientation.explain())
    if beyond_tip is not None and not reversed_:      # the segmenter may have lost a stretch before the tip
        why.append(beyond_tip.explain())
    elif continuation is not None and continuation.tip_in_doubt:
        why.append(continuation.explain())
    if doubled_tip is not None:                       # the trace may stop at a bend, short of the tip
        why.append(doubled_tip.explain())
    if tip_fork is not None and not reversed_:        # the trace took one of two ends
        why.append(tip_fork.explain())
    if catheter_end is not None:                      # the trace is the catheter's: the wire beyond it is not seen
        why.append(catheter_end.explain())
    distal_uv = uv[0] if reversed_ else uv[-1]         # the output's tip, in 2D
    if image_shape is not None and len(uv) and _at_border(distal_uv, image_shape):
        why.append(f"tip not in view: the wire runs out of the image at its distal end "
                   f"(u {distal_uv[0]:.0f}, v {distal_uv[1]:.0f} px)")
    # (one view: a second view, ``method`` "biplane", sees the depth the first does not)
    stretch_px = tip_stretch_px(pixel_at_iso_mm)
    stretch_mm = (tip_stretch_mm(wire3d, uv, stretch_px=stretch_px) if getattr(wire3d, "method", "") != "biplane"
                  else 0.0)
    if stretch_mm > TIP_STRETCH_MAX_MM:
        why.append(f"tip uncertain: its vessel runs along the beam: the 3D wire's last {stretch_mm:.1f} mm project onto "
                   f"its last {stretch_px:.3g} px (limit {TIP_STRETCH_MAX_MM:g} mm), so a tip a pixel off in 2D "
                   f"lies mm off in 3D")
    tip_sigma_mm = float(wire3d.uncertainty_mm[-1]) if len(wire3d.uncertainty_mm) else 0.0
    slide = float(tip_slide_mm) if tip_slide_mm is not None else 0.0
    forward = float(forward_mm) if forward_mm is not None else 0.0
    along_mm = max(slide, forward) / math.sqrt(12.0)
    tip_total_mm = math.hypot(tip_sigma_mm, along_mm)
    if tip_total_mm > TIP_MAX_UNCERTAINTY_MM:
        where = (f"the tip's ray passes through the lumen of {slide:.1f} mm of it" if slide >= forward else
                 f"beyond the tip its vessel runs along the beam, {forward:.1f} mm more of it projecting within "
                 f"{stretch_px:.3g} px of the 2D tip than across the beam")
        parts = (f" ({tip_sigma_mm:.1f} mm across the wire, {along_mm:.1f} mm along its vessel: {where}, where one view "
                 f"does not see the wire's end)" if along_mm > 0 else "")
        why.append(f"tip uncertain: its position is known to {tip_total_mm:.1f} mm (1 sigma, limit "
                   f"{TIP_MAX_UNCERTAINTY_MM:g} mm){parts}; {wire3d.message}")
    wire_sigma_mm = wire_uncertainty_mm(wire3d)
    if wire_sigma_mm > WIRE_MAX_UNCERTAINTY_MM:
        why.append(f"wire depth uncertain: its points are known to {wire_sigma_mm:.1f} mm (median 1 sigma, limit "
                   f"{WIRE_MAX_UNCERTAINTY_MM:g} mm): one view places the wire in depth no closer than its lumen's "
                   f"width and the CTA centerline's own error allow (the tip's own 1 sigma: {tip_sigma_mm:.1f} mm)")
    retreat_mm = float(getattr(wire3d, "tree_retreat_mm", float("nan")))
    if retreat_mm > TREE_RETREAT_MAX_MM:
        why.append(f"2D trace doubtful: along the wire, its path through the vessel tree walks {retreat_mm:.0f} mm "
                   f"back towards the root (a wire advanced from the root does not: a wire that enters elsewhere, "
                   f"e.g. from the arm into a tree rooted at its aorta's lower end, needs its access point: "
                   f"--access-lps, or the access markup in Slicer; or "
                   f"the trace took the wrong way where the wire crosses itself)")
    miss_mm = np.asarray(getattr(wire3d, "lumen_miss_mm", ()), float)
    if len(miss_mm) and float(miss_mm.max()) > OFF_LUMEN_MAX_MM:
        why.append(_off_lumen_reason(wire3d))
    extra = float(getattr(wire3d, "branch_extra_cost", float("nan")))
    shift_mm = float(getattr(wire3d, "branch_tip_shift_mm", float("nan")))
    if extra < BRANCH_EXTRA_MAX and shift_mm > BRANCH_SHIFT_MIN_MM:
        why.append(f"branch ambiguous: a path through another branch of the vessel tree explains the 2D wire about as "
                   f"well (extra cost {extra:.1f}, limit {BRANCH_EXTRA_MAX:g}; over the whole wire, or up to the end of "
                   f"that branch a few px before the tip, where the CTA tree may have lost the vessel's distal end, or "
                   f"crossing into a vessel whose lumen touches the path's, which the tree joins elsewhere) and "
                   f"ends {shift_mm:.0f} mm away")
    skip_px = float(getattr(wire3d, "tip_skip_px", float("nan")))
    if skip_px > TIP_SKIP_MAX_PX:
        why.append(f"tip uncertain: the path through the vessel tree reaches the tip's vessel by a skip "
                   f"{float(wire3d.tip_skip_from_tip_px):.0f} px before the tip: there the tree route projects onto "
                   f"{skip_px:.0f} px more than the 2D wire (limit {TIP_SKIP_MAX_PX:g} px), so the tip was put in a "
                   f"vessel the wire's last px project onto but do not lead into (a side branch that overlaps the "
                   f"wire, or a trace that crossed between two limbs of a bent wire)")
    lost_mm = float(getattr(wire3d, "lost_lumen_stretch_mm", float("nan")))
    if lost_mm > LOST_LUMEN_STRETCH_MAX_MM:
        why.append(f"branch ambiguous: {lost_mm:.0f} mm of the wire also project onto {LOST_LUMEN_WORDS} "
                   f"({float(wire3d.lost_lumen_shift_mm):.1f} mm away in depth, limit "
                   f"{LOST_LUMEN_STRETCH_MAX_MM:g} mm): two vessels fused in the CTA and the tree kept one, the wire "
                   f"may run in the lost vessel")
    if motion is not None and not motion.success:
        why.append(f"motion: {motion.message}")
    if prior_was_ok and getattr(wire3d, "prior_dropped", False):
        why.append("path changed: the wire fits another path through the vessel tree much better than the previous "
                   "ok frame's (a wire moves along one path: this frame, that one or the pose is wrong)")
    if not why:
        return Verdict.OK, wire3d.message
    return Verdict.UNCERTAIN, "; ".join(why)


def wire_uncertainty_mm(wire3d) -> float:
    """The median over a 3D wire's points of their own uncertainty (``Wire3D.uncertainty_mm``, 1 sigma, mm): what
    ``frame_verdict`` holds against ``WIRE_MAX_UNCERTAINTY_MM``. 0 for a wire without points (or NaN values only)."""
    u = np.asarray(getattr(wire3d, "uncertainty_mm", ()), float)
    u = u[np.isfinite(u)]
    return float(np.median(u)) if len(u) else 0.0


def _off_lumen_reason(wire3d) -> str:
    """The ``uncertain`` reason of a wire whose rays pass more than ``OFF_LUMEN_MAX_MM`` outside the lumen
    of their tree path (``Wire3D.lumen_miss_mm``): how far, over how much of the wire, and where."""
    miss = np.asarray(wire3d.lumen_miss_mm, float)
    arc = np.asarray(wire3d.arclength_mm, float)
    off = miss > OFF_LUMEN_MAX_MM
    span_mm = float(np.sum(np.diff(arc)[off[1:] | off[:-1]])) if len(arc) == len(miss) and len(arc) > 1 else 0.0
    k = int(np.argmax(miss))
    from_tip_mm = float(arc[-1] - arc[k]) if len(arc) == len(miss) else float("nan")
    return (f"wire off its vessel: {span_mm:.0f} mm of the 3D wire lie up to {miss[k]:.1f} mm outside the lumen of the "
            f"tree path it was placed in ({from_tip_mm:.0f} mm before the tip; limit {OFF_LUMEN_MAX_MM:g} mm): the "
            f"vessel tree lacks the one the wire is in there, or the pose is off")


def tip_stretch_px(pixel_at_iso_mm: float | None) -> float:
    """``TIP_STRETCH_PX`` on a view of ``pixel_at_iso_mm`` (widened on one finer than the reference pixel,
    ``fine_pixel_factor``; None: as it is): the px over which ``tip_stretch_mm`` and ``forward_stretch_mm`` measure."""
    return TIP_STRETCH_PX * (1.0 if pixel_at_iso_mm is None else fine_pixel_factor(pixel_at_iso_mm))


def tip_stretch_mm(wire3d, wire_uv_px, *, stretch_px: float = TIP_STRETCH_PX) -> float:
    """The 3D wire's arclength (mm) over the last ``stretch_px`` (``TIP_STRETCH_PX``) px of its 2D wire (see
    ``TIP_STRETCH_MAX_MM``); ``wire_uv_px`` in the order given to the reconstruction (its first point
    is the output's tip when ``wire3d.reversed_input``). Where the 3D wire has one point per 2D point
    (a single-view reconstruction), the 2D arclength picks the points (the segment that reaches past
    ``stretch_px`` counts in proportion: a coarsely sampled curve, as the real catheter curves of
    ``bench_real_catheter`` at 12 px, is measured over the same 5 px); else its last ``ceil(stretch_px)``
    segments (the 2D wire is sampled at about 1 px). 0 for fewer than 2 points (or an object without
    ``points_lps_mm``). ``frame_verdict`` passes ``TIP_STRETCH_PX`` widened on a view finer than
    ``geometry.REFERENCE_PIXEL_AT_ISO_MM`` (``fine_pixel_factor``)."""
    X = np.asarray(getattr(wire3d, "points_lps_mm", np.zeros((0, 3))), float).reshape(-1, 3)
    if len(X) < 2:
        return 0.0
    uv = np.asarray(wire_uv_px, float).reshape(-1, 2)
    k = int(np.ceil(stretch_px))
    last = 1.0                            # the fraction of the k-th segment (from the tip) within stretch_px
    if len(uv) == len(X):                 # walk back from the tip until stretch_px of the 2D wire (a few points:
        m = min(len(uv), 4 * k + 1)       # plain floats are faster than array calls here)
        tip_first = (uv[:m] if getattr(wire3d, "reversed_input", False) else uv[:-m - 1:-1]).tolist()
        walked, k = 0.0, 0
        while walked < stretch_px and k < m - 1:
            step = math.dist(tip_first[k], tip_first[k + 1])
            last = min(1.0, (stretch_px - walked) / step) if step > 0 else 1.0
            walked += step
            k += 1
    k = min(k, len(X) - 1)
    tail = X[len(X) - 1 - k:][::-1].tolist()   # tip first
    return float(sum(math.dist(tail[i], tail[i + 1]) * (last if i == k - 1 else 1.0) for i in range(k)))


def _at_border(uv_px, shape) -> bool:
    """Whether a point ``(u, v)`` lies within ``TIP_BORDER_PX`` of the border of an image of ``shape`` (rows, cols)."""
    u, v = float(uv_px[0]), float(uv_px[1])
    rows, cols = shape
    return min(u, v, cols - 1 - u, rows - 1 - v) <= TIP_BORDER_PX


def _finite_or_none(x):
    x = float(x)
    return round(x, 5) if np.isfinite(x) else None


def _no_wire(message: str):
    return OrderedWire(points_uv_px=np.zeros((0, 2)), success=False, message=message)
