"""The viewer's behaviour as plain methods (no window, no callbacks): frames, pose correction, export.

``ViewerController`` holds the current frame and pose of a ``ViewerCase``. When it was given
scene handles (``scene.build_scene``) it updates them in place; rendering is left to the caller
(the app renders after each key, tests render when they want).
"""
from __future__ import annotations

import enum
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from guidewire3d import registration
from guidewire3d.app import biplane as bp
from guidewire3d.app import export as ex
from guidewire3d.app.outdir import (
    PlaneB,
    PlaneBFrame,
    ViewerCase,
    WireFrame,
    display_images_uint8,
    load_cta,
    save_registration,
)
from guidewire3d.errors import InputError
from guidewire3d.geometry import Pose
from guidewire3d.live import session as live
from guidewire3d.registration import Verdict
from guidewire3d.viewer import scene as sc
from guidewire3d.viewer.scene import WIRE_RADIUS_MM

__all__ = ["Axis", "Step", "ExportKind", "ViewerController", "STEP_MM", "STEP_DEG"]


class Axis(enum.Enum):
    """Detector-frame axes: image columns ``e_u``, image rows ``e_v`` and the beam (depth)."""

    U = 0
    V = 1
    BEAM = 2


class Step(enum.Enum):
    COARSE = "coarse"
    FINE = "fine"


class ExportKind(enum.Enum):
    CURRENT_WIRE = "current_wire"
    ALL_WIRES = "all_wires"
    VESSELS = "vessels"


STEP_MM = {Step.COARSE: 5.0, Step.FINE: 0.5}
STEP_DEG = {Step.COARSE: 2.0, Step.FINE: 0.25}


class ViewerController:
    """Frame navigation, manual registration correction and export for one case.

    Parameters
    ----------
    case : ViewerCase
    scene : SceneHandles, optional
        Updated in place on every change.
    export_dir : path-like, optional
        Where exports and screenshots go (default ``case.out_dir / "exports"``).
    persist : bool, keyword-only
        Save every pose change to ``registration.json`` (default True).
    plane_b : PlaneB, optional
        Plane B of a biplane case (``outdir.load_plane_b``): its live frame, 2D wire and projected
        3D wire follow the frame, its C-arm and projected centerline the pose, and :meth:`apply`
        reconstructs from both planes.
    plane_b_scene : biplane_scene.PlaneBHandles, optional
        Plane B's actors (``biplane_scene.add_plane_b``), updated in place.
    """

    def __init__(self, case: ViewerCase, scene=None, *, export_dir=None, persist: bool = True,
                 plane_b: PlaneB | None = None, plane_b_scene=None):
        self._case = case
        self._scene = scene
        self._plane_b = plane_b
        self._plane_b_scene = plane_b_scene if plane_b is not None else None
        self._images_b_u8 = (display_images_uint8(plane_b.images)
                             if plane_b is not None and plane_b.images is not None else None)
        self._export_dir = Path(export_dir) if export_dir is not None else Path(case.out_dir) / "exports"
        self._persist = persist
        self._frame = 0
        self._step = Step.COARSE
        self._playing = False
        self._status = ""
        self._original_wires = case.wires
        self._wires_pose = case.automatic_pose  # report.json wires come from the automatic registration
        # the pose covariance enters the wires' uncertainty; it belongs to one pose (the automatic
        # registration's, then each refinement's) and is dropped for a hand-nudged pose
        self._covariance_pose = case.automatic_pose
        self._covariance = _covariance_from(case.registration)
        self._images_u8 = display_images_uint8(case.images) if case.images is not None else None
        self._roadmap_u8 = (display_images_uint8(case.roadmap_image[None])[0]
                            if case.roadmap_image is not None else None)
        self._show_roadmap = False
        self._cta_actor = None
        self._cta_slices = None
        self._residual_cache: tuple[Pose, float] | None = None
        if case.messages:
            self._status = "; ".join(case.messages)
        if scene is not None:
            self._refresh_pose()
            self.set_frame(0)

    # --- state ------------------------------------------------------------------------
    @property
    def case(self) -> ViewerCase:
        return self._case

    @property
    def pose(self) -> Pose:
        return self._case.pose

    @property
    def pose_source(self) -> str:
        return self._case.pose_source

    @property
    def frame_index(self) -> int:
        return self._frame

    @property
    def n_frames(self) -> int:
        return self._case.n_frames

    @property
    def step(self) -> Step:
        return self._step

    @property
    def playing(self) -> bool:
        return self._playing

    @property
    def status(self) -> str:
        return self._status

    @property
    def plane_b(self) -> PlaneB | None:
        """Plane B of a biplane case (None for one view)."""
        return self._plane_b

    @property
    def plane_b_scene(self):
        """Plane B's actors (``biplane_scene.PlaneBHandles``), None for one view or without a scene."""
        return self._plane_b_scene

    @property
    def plane_b_frame(self) -> PlaneBFrame | None:
        """Plane B's side of the current pair (None for one view or an unrecorded frame)."""
        if self._plane_b is None or not self.n_frames:
            return None
        return self._plane_b.frame_for(self._case.frame_indices[self._frame])

    @property
    def plane_b_image_index(self) -> int | None:
        """The index of plane B's live frame shown with the current frame (None for one view)."""
        if self._plane_b is None or not self.n_frames:
            return None
        return self._plane_b.image_index(self._case.frame_indices[self._frame])

    @property
    def wire(self) -> WireFrame | None:
        """The reconstructed wire at the current position (None when the case has no wires)."""
        return self._case.wires[self._frame] if self._frame < len(self._case.wires) else None

    @property
    def window_size_px(self) -> tuple[int, int]:
        """The scene's window size ``(w, h)`` (``(0, 0)`` without a scene)."""
        return tuple(int(v) for v in self._scene.plotter.window_size) if self._scene is not None else (0, 0)

    @property
    def showing_roadmap(self) -> bool:
        return self._show_roadmap

    @property
    def view_carm(self):
        """The C-arm of what the 2D view shows: the roadmap's when it is shown, else the live frames'."""
        return self._case.carm if self._show_roadmap else self._case.frames_carm

    @property
    def wires_stale(self) -> bool:
        """True when the pose changed since the wires were reconstructed (``apply`` re-runs them)."""
        return not self._wires_pose.allclose(self.pose, atol_mm=1e-6, atol_rad=1e-9)

    def notify(self, text: str) -> None:
        """Put ``text`` on the status line."""
        self._say(text)

    def _say(self, text: str) -> None:
        self._status = text
        self._refresh_text()

    # --- frames -----------------------------------------------------------------------
    def set_frame(self, k: int) -> int:
        """Show frame position ``k`` (clamped); the wire tube and the texture change in place."""
        n = self.n_frames
        if n == 0:
            self._frame = 0
            self._refresh_text()
            return 0
        k = int(np.clip(int(k), 0, n - 1))
        self._frame = k
        if self._scene is not None:
            w = self.wire
            if w is not None:
                sc.update_wire(self._scene.wire, w.points_lps_mm, w.uncertainty_mm)
            self._refresh_image()
            self._refresh_image_b()
            if self.wire is not None and self.wire.pose is not None:
                self._refresh_pose()  # a tracked run: the C-arm and overlays follow the frame's pose
            else:
                self._refresh_overlay_wire()
                self._refresh_text()
        return k

    @property
    def shown_pose(self) -> Pose:
        """The pose the scene shows: the current frame's tracked pose (a ``--track-motion`` run,
        wires current, live frame shown), else :attr:`pose`."""
        w = self.wire
        if w is not None and w.pose is not None and not self._show_roadmap and not self.wires_stale:
            return w.pose
        return self.pose

    def _refresh_image(self) -> None:
        if self._scene is None:
            return
        if self._show_roadmap and self._roadmap_u8 is not None:
            sc.set_frame_image(self._scene, self._roadmap_u8)
            return
        idx = self._case.frame_indices[self._frame] if self.n_frames else 0
        if self._images_u8 is not None and idx < len(self._images_u8):
            sc.set_frame_image(self._scene, self._images_u8[idx])

    def _refresh_image_b(self) -> None:
        hb = self._plane_b_scene
        k = self.plane_b_image_index
        if hb is None or k is None or self._images_b_u8 is None:
            return
        sc.set_texture_image(hb.carm.texture_image, self._images_b_u8[min(k, len(self._images_b_u8) - 1)])

    def toggle_roadmap(self) -> bool:
        """Show the contrast roadmap (what the registration matched) instead of the live frame, or back."""
        if self._roadmap_u8 is None and not self._show_roadmap:
            self._say("no roadmap image available")
            return False
        self._show_roadmap = not self._show_roadmap
        ov = self._scene.overlay if self._scene is not None else None
        if ov is not None and ov.roadmap_centerline_actor is not None:
            ov.roadmap_centerline_actor.SetVisibility(self._show_roadmap)
        self._refresh_pose()
        self._refresh_image()
        self._say("showing the roadmap" if self._show_roadmap else "showing the live frames")
        return self._show_roadmap

    def next_frame(self, *, wrap: bool = True) -> int:
        n = max(self.n_frames, 1)
        k = self._frame + 1
        return self.set_frame(k % n if wrap else min(k, n - 1))

    def previous_frame(self, *, wrap: bool = True) -> int:
        n = max(self.n_frames, 1)
        k = self._frame - 1
        return self.set_frame(k % n if wrap else max(k, 0))

    def toggle_play(self) -> bool:
        self._playing = not self._playing
        self._refresh_text()
        return self._playing

    def toggle_cta(self) -> bool:
        """Show or hide three orthogonal CTA slices through the vessel centroid (loaded on first use)."""
        if self._scene is None:
            raise InputError("CTA slices need a scene (the controller was built without one)")
        if self._cta_actor is None:
            vol = load_cta(self._case)
            pl = self._scene.plotter
            if len(pl.renderers) > 1:
                pl.subplot(0, 0)
            self._cta_slices, self._cta_actor = sc.add_cta_slices(pl, vol, self._case.centroid_lps_mm)
            self._say("CTA slices through the vessel centroid (9: hide)")
            return True
        vis = not bool(self._cta_actor.GetVisibility())
        self._cta_actor.SetVisibility(vis)
        self._say("CTA slices shown" if vis else "CTA slices hidden")
        return vis

    @property
    def cta_actor(self):
        return self._cta_actor

    @property
    def cta_slices(self):
        """The slice surfaces (``pyvista.PolyData`` with point data ``HU``), None until first shown."""
        return self._cta_slices

    # --- pose correction --------------------------------------------------------------
    def set_step(self, step: Step) -> None:
        self._step = Step(step)
        self._refresh_text()

    def toggle_step(self) -> Step:
        self.set_step(Step.FINE if self._step is Step.COARSE else Step.COARSE)
        return self._step

    def nudge(self, axis: Axis, steps: float = 1.0, *, mm: float | None = None) -> Pose:
        """Translate the vessels along a detector axis by ``steps`` of the current step (or ``mm``)."""
        axis = Axis(axis)
        amount = float(mm) if mm is not None else float(steps) * STEP_MM[self._step]
        t = np.zeros(3)
        t[axis.value] = amount
        pose = registration.nudge(self.pose, self.view_carm, centroid_lps_mm=self._case.centroid_lps_mm,
                                  translate_mm=tuple(t), rotate_deg=(0.0, 0.0, 0.0))
        self._set_pose(pose, "manual", f"moved {amount:+.2f} mm along {axis.name.lower()}")
        return pose

    def rotate(self, axis: Axis, steps: float = 1.0, *, deg: float | None = None) -> Pose:
        """Rotate the vessels about a detector axis through the vessel centroid."""
        axis = Axis(axis)
        amount = float(deg) if deg is not None else float(steps) * STEP_DEG[self._step]
        r = np.zeros(3)
        r[axis.value] = amount
        pose = registration.nudge(self.pose, self.view_carm, centroid_lps_mm=self._case.centroid_lps_mm,
                                  translate_mm=(0.0, 0.0, 0.0), rotate_deg=tuple(r))
        self._set_pose(pose, "manual", f"rotated {amount:+.2f} deg about {axis.name.lower()}")
        return pose

    def _require_registration_inputs(self, what: str) -> None:
        if self._case.tree is None or len(self._case.centerline_uv_px) == 0:
            raise InputError(f"{self._case.out_dir / 'registration_inputs.npz'}: missing, cannot {what}")

    def residual_px(self) -> float:
        """Registration residual (px) of the current pose on the roadmap centerline (``registration.score``)."""
        if self._case.tree is None or len(self._case.centerline_uv_px) == 0:
            return float("nan")
        if self._residual_cache is not None and self._residual_cache[0] is self.pose:
            return self._residual_cache[1]
        val = float(registration.score(self._case.tree, self._case.centerline_uv_px, self._case.carm, self.pose))
        self._residual_cache = (self.pose, val)
        return val

    def inlier_residual_px(self) -> float:
        """The registration's own residual of the current pose: mean over 2D points within 3 px
        (``registration.score(..., inliers_only=True)``, equal to ``RegistrationResult.mean_residual_px``)."""
        if self._case.tree is None or len(self._case.centerline_uv_px) == 0:
            return float("nan")
        cache = getattr(self, "_inlier_cache", None)
        if cache is not None and cache[0] is self.pose:
            return cache[1]
        val = float(registration.score(self._case.tree, self._case.centerline_uv_px, self._case.carm, self.pose,
                                       inliers_only=True))
        self._inlier_cache = (self.pose, val)
        return val

    @property
    def refines_both_planes(self) -> bool:
        """True when :meth:`refine` fits both roadmaps (a biplane case whose output folder keeps
        plane B's roadmap centerline)."""
        pb = self._plane_b
        return pb is not None and len(pb.centerline_uv_px) >= 10

    def refine(self):
        """Run the LM refinement from the current pose; adopt it and re-reconstruct unless it failed
        (a pose the overlay fits but the roadmap leaves uncertain is adopted with a warning).
        A biplane case is refined on both roadmaps at once (the joint problem of
        ``biplane.register_biplane``, from the current pose, as the Slicer module does), when the
        output folder keeps plane B's roadmap centerline; otherwise on plane A's, and it says so.

        Returns
        -------
        RegistrationResult
            As returned by ``registration.refine`` or the joint refinement (its ``success`` /
            ``message`` say how it went).
        """
        self._require_registration_inputs("refine")
        t0 = time.perf_counter()
        case, pb, both = self._case, self._plane_b, self.refines_both_planes
        if both:
            res = bp.register_biplane(case.tree, [case.centerline_uv_px, pb.centerline_uv_px], [case.carm, pb.carm],
                                      centerline_radius_px=(case.centerline_radius_px, pb.centerline_radius_px),
                                      init_pose=self.pose, global_search=False).result
        else:
            res = registration.refine(case.tree, case.centerline_uv_px, case.carm, self.pose,
                                      centerline_radius_px=case.centerline_radius_px)
        note = ("" if pb is None or both else
                "; plane A's roadmap alone (this output folder does not keep plane B's roadmap centerline)")
        dt = time.perf_counter() - t0
        if res.verdict is registration.Verdict.FAILED:
            self._say(f"refine failed: {res.message} (pose kept){note}")
            return res
        # "uncertain": the overlay fits best there, but the roadmap leaves the pose open (e.g. the
        # depth of a single vessel path): adopt it and say so
        self._covariance_pose, self._covariance = res.pose, res.covariance_6x6
        what = "both planes" if both else "the roadmap"
        self._set_pose(res.pose, "manual", f"refined on {what} in {dt:.2f} s: {res.mean_residual_px:.2f} px{note}")
        self.apply()
        if not res.success:
            self._say(f"{self.status}; refined, but the roadmap does not settle the pose, check it: {res.message}")
        return res

    def reset(self) -> Pose:
        """Go back to the automatic pose and its wires."""
        self._set_pose(self._case.automatic_pose, "automatic", "reset to the automatic registration")
        if self.wires_stale:
            self._case = self._case.with_wires(self._original_wires)
            self._wires_pose = self._case.automatic_pose
            self.set_frame(self._frame)
        return self.pose

    def apply(self, *, force: bool = False) -> int:
        """Reconstruct every frame's wire again with the current pose, through ``live.Session`` (the
        engine ``reconstruct`` runs), from each frame's 2D wire and image; a biplane case through
        ``biplane.BiplaneSession`` from both planes' 2D wires (plane B's records are renewed too).

        Returns the number of frames reconstructed (0 when the wires are current, unless ``force``,
        or there is no vessel tree).
        """
        if not self.wires_stale and not force:
            self._say("wires already use this pose")
            return 0
        if self._case.tree is None:
            self._say("no vessel tree: wires not reconstructed")
            return 0
        t0 = time.perf_counter()
        cov = self._covariance if np.allclose(self._covariance_pose.matrix, self.pose.matrix) else None
        if self._plane_b is not None:
            (new, n_ok), what = self._apply_biplane(cov), "pairs from both planes"
        else:
            (new, n_ok), what = self._apply_one_view(cov), "frames"
        self._case = self._case.with_wires(new)
        self._wires_pose = self.pose
        self.set_frame(self._frame)
        self._say(f"reconstructed {n_ok}/{len(new)} {what} with the {self.pose_source} pose "
                  f"in {time.perf_counter() - t0:.2f} s")
        return len(new)

    def _apply_one_view(self, cov) -> tuple[list, int]:
        """Every frame again through ``live.Session.process_wire`` (its recorded 2D wire)."""
        new, n_ok = [], 0
        # a run that tracked motion is applied the same way (each frame in its own pose)
        tracked = any(w.pose is not None for w in self._case.wires)
        session = live.Session(self._case.tree, self._case.frames_carm, self.pose, registration_covariance=cov,
                               track_motion=tracked)
        images = self._case.images
        for w in self._case.wires:
            if len(w.wire_uv_px) < 2:
                new.append(w)
                continue
            image = images[w.index] if images is not None and w.index < len(images) else None
            fr = session.process_wire(w.wire_uv_px, image=image, index=w.index)
            r = fr.wire3d
            ok = bool(r.success)
            n_ok += ok
            pts = np.asarray(r.points_lps_mm, float).reshape(-1, 3)
            unc = np.asarray(r.uncertainty_mm, float).reshape(-1)
            new.append(WireFrame(w.index, ok, str(fr.message), pts, unc, w.wire_uv_px,
                                 float(r.projection_error_px), float(r.length_mm), verdict=fr.verdict.value,
                                 pose=fr.pose if fr.motion is not None else None))
        return new, n_ok

    def _apply_biplane(self, cov) -> tuple[list, int]:
        """Every pair again through ``BiplaneSession.process_wires`` (both planes' recorded 2D wires)."""
        pb = self._plane_b
        # a run that tracked motion is applied the same way (each pair in its own tracked pose), as one view is
        tracked = any(w.pose is not None for w in self._case.wires)
        session = bp.BiplaneSession(self._case.tree, (self._case.frames_carm, pb.frames_carm), self.pose,
                                    registration_covariance=cov, threads=1, track_motion=tracked)
        new, frames_b, n_ok = [], dict(pb.frames), 0
        try:
            for w in self._case.wires:
                fb = pb.frame_for(w.index)
                k_b = pb.image_index(w.index)
                uv_b = fb.wire_uv_px if fb is not None else np.zeros((0, 2))
                img_a = self._case.images[w.index] if self._case.images is not None and w.index < len(self._case.images) \
                    else None
                img_b = pb.images[k_b] if pb.images is not None and k_b < len(pb.images) else None
                wire_a = w.wire_uv_px if len(w.wire_uv_px) >= 2 else None
                wire_b = uv_b if len(uv_b) >= 2 else None
                if wire_a is None and wire_b is None:
                    new.append(w)
                    continue
                pair = session.process_wires(wire_a, wire_b, images=(img_a, img_b), index=w.index, index_b=k_b)
                fr, r = pair.result, pair.result.wire3d
                ok = bool(r.success)
                n_ok += ok
                pts = np.asarray(r.points_lps_mm, float).reshape(-1, 3) if ok else np.zeros((0, 3))
                unc = np.asarray(r.uncertainty_mm, float).reshape(-1) if ok else np.zeros(0)
                new.append(WireFrame(w.index, ok, str(fr.message), pts, unc, w.wire_uv_px,
                                     float(r.projection_error_px), float(r.length_mm), verdict=fr.verdict.value,
                                     pose=fr.pose if fr.motion is not None else None))
                frames_b[w.index] = PlaneBFrame(k_b, pair.views, pair.fallback, uv_b, *map(float, pair.projection_error_px))
        finally:
            session.close()
        self._plane_b = replace(pb, frames=frames_b)
        return new, n_ok

    def _set_pose(self, pose: Pose, source: str, what: str) -> None:
        self._case = self._case.with_pose(pose, source=source)
        saved = ""
        if self._persist:
            try:
                p = save_registration(self._case.out_dir, pose, source=source, carm=self._case.carm,
                                      automatic_pose=self._case.automatic_pose, registration=self._case.registration)
                saved = f"; pose saved to {p}"
            except OSError as e:
                saved = f"; pose NOT saved ({e.__class__.__name__}: {e})"
        self._refresh_pose()
        self._say(what + saved)

    # --- scene refresh ----------------------------------------------------------------
    def _refresh_pose(self) -> None:
        if self._scene is None:
            return
        pose = self.shown_pose
        sc.update_carm(self._scene.carm, self.view_carm, pose)
        if self._scene.overlay is not None and self._case.tree is not None:
            sc.update_overlay(self._scene.overlay,
                              centerline_uv_px=self.view_carm.project(self._case.tree.points_lps_mm, pose))
        hb = self._plane_b_scene
        if hb is not None:  # one patient pose for both planes
            carm_b = self._plane_b.frames_carm
            sc.update_carm(hb.carm, carm_b, pose)
            if hb.overlay is not None and self._case.tree is not None:
                sc.update_overlay(hb.overlay, centerline_uv_px=carm_b.project(self._case.tree.points_lps_mm, pose))
        self._refresh_overlay_wire()
        self._refresh_text()

    def _refresh_overlay_wire(self) -> None:
        self._refresh_overlay_wire_b()
        if self._scene is None or self._scene.overlay is None:
            return
        w = self.wire
        if w is None or self._show_roadmap:
            sc.update_overlay(self._scene.overlay, wire_uv_px=np.zeros((0, 2)), wire_proj_uv_px=np.zeros((0, 2)))
            return
        proj = (self._case.frames_carm.project(w.points_lps_mm, self.shown_pose) if len(w.points_lps_mm)
                else np.zeros((0, 2)))
        sc.update_overlay(self._scene.overlay, wire_uv_px=w.wire_uv_px, wire_proj_uv_px=proj)

    def _refresh_overlay_wire_b(self) -> None:
        hb = self._plane_b_scene
        if hb is None or hb.overlay is None:
            return
        w, fb = self.wire, self.plane_b_frame
        uv = fb.wire_uv_px if fb is not None else np.zeros((0, 2))
        proj = (self._plane_b.frames_carm.project(w.points_lps_mm, self.shown_pose)
                if w is not None and len(w.points_lps_mm) else np.zeros((0, 2)))
        sc.update_overlay(hb.overlay, wire_uv_px=uv, wire_proj_uv_px=proj)
        sc.set_text(hb.info_text, self.info_text_b())

    def info_text_b(self) -> str:
        """Plane B's 2D view caption: its frame, which planes made the wire, both projection errors."""
        k, fb = self.plane_b_image_index, self.plane_b_frame
        if k is None:
            return ""
        parts = [f"PLANE B frame {k}"]
        if fb is None:
            parts.append("no plane B record for this frame")
            return "\n".join(parts)

        def px(x):
            return f"{x:.2f} px" if np.isfinite(x) else "n/a"

        parts.append(f"3D wire from {'planes ' + ' + '.join(fb.views) if fb.views else 'no plane'}"
                     + ("" if len(fb.wire_uv_px) >= 2 else "; no 2D wire in plane B"))
        parts.append(f"projection error A {px(fb.projection_error_px_a)}, B {px(fb.projection_error_px_b)}")
        if fb.fallback:
            msg = " ".join(fb.fallback.split())
            parts.append(msg[:52] + "..." if len(msg) > 55 else msg)
        if self.wires_stale:
            parts.append("(wires stale: Return)")
        return "\n".join(parts)

    def info_text(self) -> str:
        w = self.wire
        res = self.residual_px()
        if self._show_roadmap:
            parts = ["ROADMAP (cyan: its 2D centerline; a: back to live)"]
        elif self.n_frames:
            idx = self._case.frame_indices[self._frame]
            parts = [f"frame {idx} [{self._frame + 1} of {self.n_frames}]" + (" (playing)" if self._playing else "")]
        else:
            parts = ["no live frames"]
        if not self._case.wires:
            parts.append("no reconstructed wires in this folder")
        if np.isfinite(res):
            inl = self.inlier_residual_px()
            parts.append(f"residual {res:.2f} px over the whole 2D centerline"
                         + (f", {inl:.2f} px over inliers (as registered)" if np.isfinite(inl) else ", no inliers"))
        else:
            parts.append("residual n/a")
        parts.append(f"pose {self.pose_source}" + (" (wires stale: Return)" if self.wires_stale else ""))
        reg = self._case.registration
        if self.pose_source == "automatic" and reg and not reg.get("success", True):
            if reg.get("verdict") == Verdict.UNCERTAIN:
                parts.append("AUTOMATIC REGISTRATION UNCERTAIN: the overlay fits, the roadmap does not settle "
                             "the pose" + (" (one vessel path: depth)" if reg.get("single_path") else ""))
            else:
                parts.append("AUTOMATIC REGISTRATION FAILED: check the overlay, correct, refine (o)")
        parts.append(f"step {self._step.value} ({STEP_MM[self._step]:g} mm / {STEP_DEG[self._step]:g} deg)")
        parts.append("yellow: CTA centerline; magenta: 2D wire; green: 3D wire")
        if w is not None:
            if len(w.points_lps_mm) > 1:
                parts.append(f"wire {w.length_mm:.1f} mm, max unc. {np.max(w.uncertainty_mm):.2f} mm"
                             if len(w.uncertainty_mm) else f"wire {w.length_mm:.1f} mm")
            if not w.success:
                msg = " ".join(w.message.split())
                parts.append(f"frame failed: {msg[:52] + '...' if len(msg) > 55 else msg}")
        return "\n".join(parts)

    def _refresh_text(self) -> None:
        if self._scene is None:
            return
        sc.set_text(self._scene.info_text, self.info_text())
        sc.set_text(self._scene.status_text, self._status)

    # --- export -----------------------------------------------------------------------
    def export(self, kind: ExportKind, directory=None) -> list[Path]:
        """Write STL and VTP (LPS mm) of the current wire, all wires, or the vessels.

        Returns the written paths; the status line says where they went.
        """
        kind = ExportKind(kind)
        out = Path(directory) if directory is not None else self._export_dir
        written: list[Path] = []
        if kind is ExportKind.VESSELS:
            if self._case.vessels_path is None:
                raise InputError(f"{self._case.out_dir}: no vessels.vtp/.stl to export")
            surf = ex.read_polydata(self._case.vessels_path)
            for ext in ("vtp", "stl"):
                written.append(ex.write_polydata(surf, out / f"vessels.{ext}"))
        else:
            wires = [self.wire] if kind is ExportKind.CURRENT_WIRE else list(self._case.wires)
            wires = [w for w in wires if w is not None and len(w.points_lps_mm) >= 2]
            if not wires:
                raise InputError(f"frame {self._frame}: no reconstructed wire to export")
            for w in wires:
                line = ex.wire_polydata(w)
                written.append(ex.write_polydata(line, out / f"guidewire_{w.index:04d}.vtp"))
                written.append(ex.write_polydata(ex.tube_polydata(line, WIRE_RADIUS_MM), out / f"guidewire_{w.index:04d}.stl"))
        self._say(f"exported {len(written)} files to {out}")
        return written

    def _fit_2d_cameras(self) -> None:
        if self._scene.renderer_2d is not None:
            sc.fit_2d_camera(self._scene.renderer_2d, self._case.frames_carm.shape)
        hb = self._plane_b_scene
        if hb is not None and hb.renderer_2d is not None:
            sc.fit_2d_camera(hb.renderer_2d, self._plane_b.frames_carm.shape)

    def screenshot(self, path=None, *, size_px=None, announce: bool = True) -> Path:
        """Render the current view to a PNG (at ``size_px=(w, h)`` if given) and return its path."""
        if self._scene is None:
            raise InputError("screenshot needs a scene (the controller was built without one)")
        path = Path(path) if path is not None else self._export_dir / f"screenshot_frame{self._frame:04d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        pl = self._scene.plotter
        old = tuple(pl.window_size)
        if announce:
            self._say(f"screenshot: {path}")
        if size_px is not None:
            pl.window_size = tuple(int(s) for s in size_px)
        self._fit_2d_cameras()
        pl.render()
        img = pl.screenshot(None, return_img=True)
        if size_px is not None:
            pl.window_size = old
            self._fit_2d_cameras()
            pl.render()
        return sc.write_png(path, img)


def _covariance_from(registration: dict):
    """The ``covariance_6x6`` of a registration record, or None."""
    c = (registration or {}).get("covariance_6x6")
    try:
        c = np.asarray(c, float)
    except (TypeError, ValueError):
        return None
    return c if c.shape == (6, 6) and np.all(np.isfinite(c)) else None
