"""The desktop viewer: builds the scene, wires keys and sliders to the controller, shows the window.

``guidewire3d view OUT_DIR`` (or ``--cta/--roadmap/--frames [--access-lps]`` to run the pipeline first; a folder
written by ``guidewire3d vessels`` shows its vessel plan, ``plan_scene``);
``--screenshot PATH`` renders offscreen and exits. Keys are listed on screen (``scene.HELP``).
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

from guidewire3d.app import igtl, pipeline
from guidewire3d.app.outdir import load_outdir
from guidewire3d.errors import Guidewire3DError, InputError
from guidewire3d.viewer import plan_scene
from guidewire3d.viewer import scene as sc
from guidewire3d.viewer.biplane_scene import add_plane_b, plane_b_of_outdir
from guidewire3d.viewer.controller import Axis, ExportKind, ViewerController

__all__ = ["parse_size", "open_viewer", "render_outdir_screenshot", "run_interactive", "cli_main", "KEYS",
           "LiveFollower", "run_live"]

DEFAULT_SIZE = (1200, 800)
PLAY_INTERVAL_MS = 50


def parse_size(text) -> tuple[int, int]:
    """``"1200x800"`` -> ``(1200, 800)``; raises InputError naming ``--size`` otherwise."""
    if isinstance(text, (tuple, list)):
        w, h = text
    else:
        try:
            w, h = (int(v) for v in str(text).lower().split("x"))
        except ValueError:
            raise InputError(f"--size: expected WxH such as 1200x800, got {text!r}") from None
    w, h = int(w), int(h)
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise InputError(f"--size: width and height must be within 16..8192, got {w}x{h}")
    return w, h


def _prepare_offscreen_env() -> None:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def open_viewer(out_dir, *, size_px=DEFAULT_SIZE, off_screen: bool = False, frame: int = 0, persist: bool = True):
    """Load ``out_dir``, build the two-view scene and its controller.

    A biplane output folder gets three views: 3D on the left, plane A's 2D view top right and plane
    B's bottom right (``ctl.plane_b`` and ``ctl.plane_b_scene`` hold plane B's data and actors).

    Returns
    -------
    (ViewerController, SceneHandles)
    """
    import pyvista as pv

    if off_screen:
        _prepare_offscreen_env()
    case = load_outdir(out_dir)
    plane_b = plane_b_of_outdir(out_dir)
    vessels = pv.read(str(case.vessels_path)) if case.vessels_path is not None else None
    pl = sc.new_plotter(size_px=size_px, off_screen=off_screen, biplane=plane_b is not None,
                        title=f"guidewire3d: {Path(out_dir).name}")
    w0 = case.wires[0] if case.wires else None
    handles = sc.build_scene(
        pl, carm=case.frames_carm, pose=case.pose, vessels=vessels, tree=case.tree,
        wire_points_lps_mm=None if w0 is None else w0.points_lps_mm,
        wire_uncertainty_mm=None if w0 is None else w0.uncertainty_mm,
        roadmap_centerline_uv_px=case.centerline_uv_px,
    )
    # biplane output (issue 23): plane B's C-arm in the 3D view, its 2D view below plane A's
    hb = add_plane_b(pl, plane_b, case.pose, tree=case.tree) if plane_b is not None else None
    ctl = ViewerController(case, handles, persist=persist, plane_b=plane_b, plane_b_scene=hb)
    if frame:
        if case.n_frames and not 0 <= frame < case.n_frames:
            raise InputError(f"--frame: {frame} is out of range (the case has {case.n_frames} frames)")
        ctl.set_frame(frame)
    return ctl, handles


def render_outdir_screenshot(out_dir, path, *, frame: int | None = None, size=DEFAULT_SIZE) -> Path:
    """Render the viewer offscreen for ``out_dir`` at ``frame`` and write a PNG to ``path``."""
    ctl, handles = open_viewer(out_dir, size_px=parse_size(size), off_screen=True, frame=int(frame or 0),
                               persist=False)
    try:
        return ctl.screenshot(path, announce=False)
    finally:
        handles.plotter.close()


# key -> (description, controller action); actions take the controller
def _keys():
    return {
        "n": ("next frame", lambda c: c.next_frame()),
        "N": ("previous frame", lambda c: c.previous_frame()),
        "space": ("play / pause", lambda c: c.toggle_play()),
        "g": ("coarse / fine step", lambda c: c.toggle_step()),
        "a": ("roadmap / live frame in the 2D view", lambda c: c.toggle_roadmap()),
        "9": ("CTA slices on / off", lambda c: c.toggle_cta()),
        "j": ("move -u", lambda c: c.nudge(Axis.U, -1)),
        "l": ("move +u", lambda c: c.nudge(Axis.U, +1)),
        "i": ("move -v (up)", lambda c: c.nudge(Axis.V, -1)),
        "k": ("move +v (down)", lambda c: c.nudge(Axis.V, +1)),
        "d": ("move toward the detector", lambda c: c.nudge(Axis.BEAM, +1)),
        "D": ("move toward the source", lambda c: c.nudge(Axis.BEAM, -1)),
        "x": ("rotate + about u", lambda c: c.rotate(Axis.U, +1)),
        "X": ("rotate - about u", lambda c: c.rotate(Axis.U, -1)),
        "y": ("rotate + about v", lambda c: c.rotate(Axis.V, +1)),
        "Y": ("rotate - about v", lambda c: c.rotate(Axis.V, -1)),
        "z": ("rotate + about the beam", lambda c: c.rotate(Axis.BEAM, +1)),
        "Z": ("rotate - about the beam", lambda c: c.rotate(Axis.BEAM, -1)),
        "o": ("refine (LM) from this pose", lambda c: c.refine()),
        "0": ("reset to the automatic pose", lambda c: c.reset()),
        "Return": ("apply: reconstruct all frames with this pose", lambda c: c.apply()),
        "c": ("screenshot PNG (window size)", lambda c: c.screenshot()),
        "h": ("screenshot PNG at twice the window size", lambda c: c.screenshot(size_px=_twice(c))),
        "t": ("export the current wire (STL+VTP)", lambda c: c.export(ExportKind.CURRENT_WIRE)),
        "T": ("export all wires", lambda c: c.export(ExportKind.ALL_WIRES)),
        "V": ("export the vessels", lambda c: c.export(ExportKind.VESSELS)),
    }


def _twice(ctl) -> tuple[int, int]:
    w, h = ctl.window_size_px
    return 2 * w, 2 * h


KEYS = tuple(_keys())


class _App:
    """Binds keys, sliders and the play timer to a controller. Holds no logic of its own."""

    def __init__(self, ctl, handles):
        self.ctl = ctl
        self.h = handles
        self.pl = handles.plotter
        self.frame_slider = None
        self.pose_sliders = {}
        self._slider_states = {}

    def safe(self, fn, *, render: bool = True):
        """Wrap a controller action: errors go to the status line, widgets follow, then one render."""
        def run(value=None):  # keys call it with no argument, sliders with their value
            try:
                fn(self.ctl) if value is None else fn(self.ctl, value)
            except Guidewire3DError as e:
                self.ctl.notify(f"error: {' '.join(str(e).split())}")
            self.sync_widgets()
            if render:
                self.pl.render()
        return run

    def sync_widgets(self):
        if self.ctl.pose_source == "automatic":  # after a reset the slider offsets start again at 0
            for name, w in self.pose_sliders.items():
                self._slider_states[name]["last"] = 0.0
                w.GetRepresentation().SetValue(0.0)
        if self.frame_slider is not None:
            rep = self.frame_slider.GetRepresentation()
            if int(round(rep.GetValue())) != self.ctl.frame_index:
                rep.SetValue(self.ctl.frame_index)

    def bind(self):
        for key, (_, action) in _keys().items():
            self.pl.add_key_event(key, self.safe(action))
        self.pl.add_key_event("7", lambda: (sc.beams_eye_camera(self.h.renderer_3d, self.ctl.view_carm,
                                                                self.ctl.pose), self.pl.render()))
        self.pl.add_key_event("8", lambda: (self._overview(), self.pl.render()))
        self.pl.subplot(0, 0)
        n = self.ctl.n_frames
        if n > 1:
            def on_frame(ctl, value):
                k = int(round(value))
                if k != ctl.frame_index:
                    ctl.set_frame(k)
            self.frame_slider = self.pl.add_slider_widget(
                self.safe(on_frame, render=False), [0, n - 1], value=self.ctl.frame_index, title="frame", pointa=(0.06, 0.07),
                pointb=(0.44, 0.07), interaction_event="always", fmt="%.0f", style="modern", title_height=0.02)
        self.pl.subplot(0, 1)  # slider points are normalised to this viewport: plane A's 2D view
        self._add_pose_slider("u", "U", (0.56, 0.21), (0.76, 0.21), 20.0)
        self._add_pose_slider("v", "V", (0.78, 0.21), (0.98, 0.21), 20.0)
        self._add_pose_slider("depth", "BEAM", (0.56, 0.08), (0.76, 0.08), 60.0)
        self._add_pose_slider("rot beam", "ROT_BEAM", (0.78, 0.08), (0.98, 0.08), 10.0)
        self.pl.subplot(0, 0)
        self.pl.iren.add_observer("TimerEvent", self._on_timer)
        for r2 in self._renderers_2d():  # before each render of a 2D view
            r2.AddObserver("StartEvent", lambda *_, r=r2: self._keep_2d_flat(r))

    def _renderers_2d(self):
        hb = self.ctl.plane_b_scene
        return [r for r in (self.h.renderer_2d, hb.renderer_2d if hb is not None else None) if r is not None]

    def _keep_2d_flat(self, r2):
        """The 2D views may pan and zoom but not rotate: put the camera back facing the image."""
        cam = r2.GetActiveCamera()
        fx, fy, _ = cam.GetFocalPoint()
        if cam.GetViewUp() != (0.0, 1.0, 0.0) or cam.GetPosition()[:2] != (fx, fy):
            cam.SetFocalPoint(fx, fy, 0.0)
            cam.SetPosition(fx, fy, 1000.0)
            cam.SetViewUp(0.0, 1.0, 0.0)
            cam.SetClippingRange(900.0, 1100.0)

    def _add_pose_slider(self, title, axis_name, a, b, half_range):
        state = {"last": 0.0}
        self._slider_states[axis_name] = state

        def on_change(ctl, value):
            delta = float(value) - state["last"]
            state["last"] = float(value)
            if abs(delta) < 1e-9:
                return
            if axis_name == "ROT_BEAM":
                ctl.rotate(Axis.BEAM, deg=delta)
            else:
                ctl.nudge(Axis[axis_name], mm=delta)

        unit = "deg" if axis_name == "ROT_BEAM" else "mm"
        self.pose_sliders[axis_name] = self.pl.add_slider_widget(
            self.safe(on_change, render=False), [-half_range, half_range], value=0.0, title=f"{title} ({unit})", pointa=a, pointb=b,
            interaction_event="always", fmt="%.1f", style="modern", title_height=0.018)

    def _overview(self):
        b = self.h.vessels_actor.GetBounds() if self.h.vessels_actor is not None else self.h.wire.actor.GetBounds()
        sc.overview_camera(self.h.renderer_3d, self.ctl.case.frames_carm, self.ctl.pose, b)

    def _on_timer(self, *_):
        if self.ctl.playing:
            self.ctl.next_frame()
            self.sync_widgets()
            self.pl.render()

    def show(self):
        self.pl.show(auto_close=False, interactive_update=True)
        self.pl.iren.create_timer(PLAY_INTERVAL_MS, repeating=True)
        self.pl.iren.start()
        self.pl.close()


def run_interactive(out_dir, *, size_px=DEFAULT_SIZE, frame: int = 0) -> int:
    """Open the viewer window on ``out_dir`` and block until it is closed."""
    import sys

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise InputError("view: no display (DISPLAY is not set); use --screenshot PATH, or run under xvfb-run")
    if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW") == "vtkEGLRenderWindow":
        del os.environ["VTK_DEFAULT_OPENGL_WINDOW"]  # EGL renders offscreen only; a window needs X
    ctl, handles = open_viewer(out_dir, size_px=size_px, off_screen=False, frame=frame)
    app = _App(ctl, handles)
    app.bind()
    app.show()
    return 0


class LiveFollower:
    """Follows a ``guidewire3d live`` server: its newest ``Guidewire`` replaces the wire tube.

    ``poll()`` (no window needed) reads what ``client`` (an ``igtl.IGTLClient``) received, updates
    the wire in place (``scene.update_wire``, with the ``GuidewireUncertainty`` of the same frame)
    and the status line; it returns True when the wire changed.
    """

    def __init__(self, wire_handles, client, *, status_text=None):
        self.wire, self.status_text = wire_handles, status_text
        self.follower = igtl.WireFollower(client)

    @property
    def status(self) -> dict:
        return self.follower.status

    @property
    def n_updates(self) -> int:
        return self.follower.n_updates

    @property
    def points_lps_mm(self):
        return None if self.follower.wire is None else self.follower.wire.points_lps_mm

    def poll(self) -> bool:
        before = dict(self.follower.status)
        got = self.follower.poll()
        s = self.follower.status
        if self.status_text is not None and s and s != before:
            sc.set_text(self.status_text, f"live frame {s.get('frame')}: {s.get('verdict')} "
                                          f"{s.get('message', '')[:70]} ({s.get('dropped', 0)} dropped)")
        if got is None:
            return False
        sc.update_wire(self.wire, got.points_lps_mm, got.uncertainty_mm)
        return True


def run_live(address, *, out_dir=None, size_px=DEFAULT_SIZE, screenshot=None, wait_s: float = 30.0) -> int:
    """``view --live HOST:PORT``: the viewer (on ``out_dir``'s scene, or the wire alone) follows a live
    server. With ``screenshot``: wait for the first wire (up to ``wait_s``), write the PNG, exit."""
    import sys
    import time

    host, port = igtl.parse_host_port(address)
    off = screenshot is not None
    if not off:
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise InputError("view --live: no display (DISPLAY is not set); use --screenshot PATH, or run under xvfb-run")
        if os.environ.get("VTK_DEFAULT_OPENGL_WINDOW") == "vtkEGLRenderWindow":
            del os.environ["VTK_DEFAULT_OPENGL_WINDOW"]
    else:
        _prepare_offscreen_env()
    try:
        client = igtl.IGTLClient(host, port, keep=64, connect_timeout_s=wait_s)
    except ConnectionError as e:
        raise InputError(f"--live {address}: {e}") from None
    try:
        if out_dir is not None:
            ctl, handles = open_viewer(out_dir, size_px=size_px, off_screen=off, persist=False)
            pl, wire, text = handles.plotter, handles.wire, handles.status_text
        else:
            import numpy as np

            ctl, handles = None, None
            pl = sc.new_plotter(size_px=size_px, off_screen=off, two_views=False, title=f"guidewire3d live {address}")
            wire = sc.add_wire(pl, np.zeros((0, 3)), np.zeros(0))
            text = sc.add_text(pl.renderer, f"waiting for {address}", top=False, font_size=11)
        follower = LiveFollower(wire, client, status_text=text)
        first = [out_dir is not None]  # without a scene the camera goes to the first wire

        def tick(*_):
            if follower.poll():
                if not first[0]:
                    pl.reset_camera()
                    first[0] = True
                pl.render()

        if off:
            end = time.monotonic() + wait_s
            while follower.n_updates == 0 and time.monotonic() < end:
                time.sleep(0.02)
                follower.poll()
            if follower.n_updates == 0:
                raise InputError(f"--live {address}: no Guidewire message within {wait_s:g} s")
            tick()
            if not first[0]:
                pl.reset_camera()
            pl.render()
            path = Path(screenshot)
            path.parent.mkdir(parents=True, exist_ok=True)
            pl.screenshot(str(path))
            pl.close()
            print(f"screenshot written to {path} (live frame {follower.status.get('frame')})")
            return 0
        if ctl is not None:
            app = _App(ctl, handles)
            app.bind()
        pl.show(auto_close=False, interactive_update=True)
        pl.iren.add_observer("TimerEvent", tick)
        pl.iren.create_timer(PLAY_INTERVAL_MS, repeating=True)
        pl.iren.start()
        pl.close()
        return 0
    finally:
        client.close()


def _run_pipeline(args) -> Path:
    """``view --cta --roadmap --frames [OUT_DIR] [--access-lps]``: ``reconstruct``'s library call
    (``pipeline.run_to_outdir``) into OUT_DIR, or a new temporary folder; the folder it wrote."""
    missing = [f"--{n}" for n in ("cta", "roadmap", "frames") if not getattr(args, n, None)]
    if missing:
        raise InputError(f"view: {', '.join(missing)} missing (give all of --cta, --roadmap, --frames, or an OUT_DIR)")
    temporary = not getattr(args, "out_dir", None)
    out = Path(tempfile.mkdtemp(prefix="guidewire3d-view-")) if temporary else Path(args.out_dir)
    try:
        pipeline.run_to_outdir(args.cta, args.roadmap, args.frames, out, access_lps_mm=getattr(args, "access_lps", None),
                               screenshot=render_outdir_screenshot)
    except BaseException:
        if temporary and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # refused or interrupted: the empty temporary folder is not left behind
        raise
    return out


def _refuse_access(args, out_dir) -> None:
    """``--access-lps`` belongs to a run: refused (one line) on a finished OUT_DIR, whose report says
    how its tree is rooted."""
    if getattr(args, "access_lps", None) is None:
        return
    try:
        rec = json.loads((Path(out_dir) / "report.json").read_text()).get("access")
    except (OSError, ValueError, AttributeError):
        rec = None
    rooted = ("at its access point " + ",".join(f"{v:g}" for v in rec["access_lps_mm"])
              if isinstance(rec, dict) and "access_lps_mm" in rec else "at its automatic root")
    raise InputError(f"--access-lps: {out_dir} is a finished reconstruction, its vessel tree rooted when it was "
                     f"written ({rooted}); give --access-lps with --cta, --roadmap and --frames, or rerun "
                     "`guidewire3d reconstruct --access-lps`")


def cli_main(args) -> int:
    """Entry point of ``guidewire3d view``; returns the exit code."""
    size = parse_size(getattr(args, "size", None) or "1200x800")
    frame = int(getattr(args, "frame", 0) or 0)
    if frame < 0:
        raise InputError(f"--frame: must be >= 0, got {frame}")
    if getattr(args, "live", None):
        if getattr(args, "access_lps", None) is not None:
            raise InputError("--access-lps: view --live shows the wires of a `guidewire3d live` server, whose tree is "
                             "rooted by that server; give --access-lps to `guidewire3d live`")
        out = Path(args.out_dir) if getattr(args, "out_dir", None) else None
        if out is not None and not (out / "report.json").is_file():
            raise InputError(f"{out}: no report.json (not a guidewire3d output folder)")
        return run_live(args.live, out_dir=out, size_px=size, screenshot=getattr(args, "screenshot", None))
    if any(getattr(args, n, None) for n in ("cta", "roadmap", "frames")):
        out_dir = _run_pipeline(args)
    elif getattr(args, "out_dir", None) and plan_scene.is_plan_folder(args.out_dir):
        # a folder written by `guidewire3d vessels`: the plan (no C-arm, no wire)
        if getattr(args, "access_lps", None) is not None:
            raise InputError(f"--access-lps: {args.out_dir} is a finished vessel plan; give --access-lps to "
                             "`guidewire3d vessels`")
        if getattr(args, "screenshot", None):
            print(f"screenshot written to {plan_scene.render_plan_screenshot(args.out_dir, args.screenshot, size=size)}")
            return 0
        return plan_scene.run_plan_interactive(args.out_dir, size_px=size)
    elif getattr(args, "out_dir", None):
        out_dir = Path(args.out_dir)
        if not (out_dir / "report.json").is_file():
            raise InputError(f"{out_dir}: no report.json (not a guidewire3d output folder)")
        _refuse_access(args, out_dir)
    else:
        raise InputError("view: give an OUT_DIR or --cta, --roadmap and --frames")
    if not (out_dir / "report.json").is_file():
        raise InputError(f"{out_dir}: no report.json (not a guidewire3d output folder)")
    if getattr(args, "screenshot", None):
        path = render_outdir_screenshot(out_dir, args.screenshot, frame=frame, size=size)
        print(f"screenshot written to {path}")
        return 0
    return run_interactive(out_dir, size_px=size, frame=frame)
