"""3D Slicer scripted module: 3D guidewire reconstruction from a CTA and single-view or biplane DSA (guidewire3d).

Layout as Slicer's scripted-module template: module metadata, a thin Widget, a Logic and a Test.
The computation lives in ``GuidewireReconstructionLib.logic`` (MRML only, no Qt), which imports
``guidewire3d``; this file imports it lazily, after ``Resources/requirements.txt`` is installed
into Slicer's Python with ``slicer.packaging.pip_ensure``.

Outside the Slicer application (``pip install slicer-core``: MRML without Qt) this file still
imports: the Qt-dependent classes are defined only when Slicer provides them.
"""
from pathlib import Path
from typing import Annotated

import slicer
import vtk

try:  # provided only by the Slicer application (Qt)
    import ctk  # noqa: F401
    import qt  # noqa: F401
    from slicer.ScriptedLoadableModule import (
        ScriptedLoadableModule,
        ScriptedLoadableModuleLogic,
        ScriptedLoadableModuleTest,
        ScriptedLoadableModuleWidget,
    )
    from slicer.parameterNodeWrapper import Choice, WithinRange, parameterNodeWrapper
    from slicer.util import VTKObservationMixin
    from slicer import (
        vtkMRMLLinearTransformNode,
        vtkMRMLMarkupsFiducialNode,
        vtkMRMLModelNode,
        vtkMRMLScalarVolumeNode,
        vtkMRMLSegmentationNode,
        vtkMRMLSequenceNode,
        vtkMRMLTableNode,
    )

    SLICER_APP = True
except ImportError:
    SLICER_APP = False

try:
    from slicer.i18n import tr as _
except ImportError:  # Slicer < 5.4 and slicer-core

    def _(text):
        return text


MODULE_DIR = Path(__file__).resolve().parent
REQUIREMENTS = MODULE_DIR / "Resources" / "requirements.txt"
#: Values of ``guidewire3d.methods.ReconMethod`` (the combo box choices; tested to match).
METHOD_CHOICES = ("vessel", "paper", "bspline")
#: Values of ``guidewire3d.xray.segmentation.SegMethod``.
SEGMENTER_CHOICES = ("unet", "ridge")


def requirements() -> list:
    """The requirement lines of ``Resources/requirements.txt`` (comments and blanks dropped)."""
    lines = REQUIREMENTS.read_text().splitlines()
    return [ln.split("#", 1)[0].strip() for ln in lines if ln.split("#", 1)[0].strip()]


def checkoutRoot():
    """The guidewire3d source checkout this module sits in (``<root>/plugin/GuidewireReconstruction``), or None."""
    root = MODULE_DIR.parents[1]
    pyproject = root / "pyproject.toml"
    if pyproject.is_file() and 'name = "guidewire3d"' in pyproject.read_text(errors="replace"):
        return root
    return None


def _importable() -> bool:
    try:
        import guidewire3d  # noqa: F401

        return True
    except ImportError:
        return False


def ensureDependencies(requester: str = "GuidewireReconstruction") -> bool:
    """Install what the module needs into Slicer's Python if missing; True when guidewire3d imports.

    1. ``Resources/requirements.txt`` through ``slicer.packaging.pip_ensure`` (asks the user, shows
       progress, offers a restart), or ``slicer.util.pip_install`` on Slicer without ``slicer.packaging``.
    2. ``guidewire3d`` from the checkout this module sits in: ``pip install --no-deps -e <checkout>``
       (``--no-deps`` keeps pip from installing a second VTK into Slicer).
    """
    if _importable():
        return True
    packaging = getattr(slicer, "packaging", None)
    if packaging is not None and hasattr(packaging, "pip_ensure"):
        packaging.pip_ensure(packaging.load_requirements(str(REQUIREMENTS)), requester=requester)
    elif SLICER_APP:
        if not slicer.util.confirmOkCancelDisplay(
            _("GuidewireReconstruction needs the guidewire3d Python package and its dependencies. Install now?")
        ):
            return False
        slicer.util.pip_install(["-r", str(REQUIREMENTS)])
    root = checkoutRoot()
    if root is not None and not _importable() and SLICER_APP:
        slicer.util.pip_install(["--no-deps", "-e", str(root)])
    import importlib

    importlib.invalidate_caches()
    return _importable()


def coreLogicClass():
    """``GuidewireReconstructionLib.logic.GuidewireReconstructionCoreLogic`` (imports guidewire3d)."""
    from GuidewireReconstructionLib.logic import GuidewireReconstructionCoreLogic

    return GuidewireReconstructionCoreLogic


def _path_or_none(p):
    s = "" if p is None else str(p).strip()
    return None if s in ("", ".") else Path(s)


if SLICER_APP:

    #
    # GuidewireReconstruction
    #

    class GuidewireReconstruction(ScriptedLoadableModule):
        """Module metadata. Base class: Slicer's ScriptedLoadableModule."""

        def __init__(self, parent):
            ScriptedLoadableModule.__init__(self, parent)
            self.parent.title = _("Guidewire Reconstruction")
            self.parent.categories = [_("Cardiac"), _("Registration")]
            self.parent.dependencies = ["Sequences", "Markups", "Models", "Transforms", "Tables"]
            self.parent.contributors = ["guidewire3d developers"]
            self.parent.helpText = _(
                "Reconstructs the guidewire in 3D from a preoperative CTA and an intraoperative DSA roadmap "
                "plus live fluoroscopy frames (single view, or biplane: give plane B's roadmap and frames too). "
                "Outputs: the vessel surface, the centerline, the "
                "registration as a linear transform (correct it with the transform handles, then press Refine), "
                "a guidewire tube and curve per frame, and a table of per-frame metrics. "
                "Extract vessels (planning) needs the CTA alone: the vessel surface, the centerline and a table of "
                "branches, one tree per vessel structure the seed points lie in. "
                "All computation is done by the guidewire3d Python package, installed on first use."
            )
            self.parent.acknowledgementText = _(
                "Method after 'Real-Time 3D Guidewire Reconstruction from Intraoperative DSA Images for "
                "Robot-Assisted Endovascular Interventions'. Module layout follows Slicer's scripted-module template."
            )

    #
    # Parameter node
    #

    @parameterNodeWrapper
    class GuidewireReconstructionParameterNode:
        """Typed module parameters (saved with the scene).

        ctaVolume: the CTA (HU). roadmapPath/framesPath: XA DICOM files; loading them creates
        roadmapSequence/framesSequence, which can also be chosen directly. An empty frames input
        means "the roadmap run". roadmapFrame -1: choose the most contrast-filled frame.
        roadmapBPath/framesBPath (or roadmapBSequence/framesBSequence): plane B of a biplane C-arm,
        optional; with plane B's roadmap the biplane chain runs (one pose, each wire from both planes).
        access: one markups point where the wire enters the vessels (the sheath tip or the puncture),
        optional; the vessel tree is rooted at its point nearest to it (transfemoral, transradial wires).
        planVesselModel/planCenterlineModel/branchesTable/planSegmentation: the outputs of "Extract vessels" (the
        CTA alone, for planning), created when empty.
        """

        ctaVolume: vtkMRMLScalarVolumeNode
        roadmapPath: Path
        framesPath: Path
        roadmapSequence: vtkMRMLSequenceNode
        framesSequence: vtkMRMLSequenceNode
        roadmapBPath: Path
        framesBPath: Path
        roadmapBSequence: vtkMRMLSequenceNode
        framesBSequence: vtkMRMLSequenceNode
        seeds: vtkMRMLMarkupsFiducialNode
        access: vtkMRMLMarkupsFiducialNode
        roadmapFrame: Annotated[int, WithinRange(-1, 99999)] = -1
        method: Annotated[str, Choice(list(METHOD_CHOICES))] = "vessel"
        segmenter: Annotated[str, Choice(list(SEGMENTER_CHOICES))] = "unet"
        force: bool = False
        trackMotion: bool = False
        registrationTransform: vtkMRMLLinearTransformNode
        metricsTable: vtkMRMLTableNode
        vesselModel: vtkMRMLModelNode
        planVesselModel: vtkMRMLModelNode
        planCenterlineModel: vtkMRMLModelNode
        branchesTable: vtkMRMLTableNode
        planSegmentation: vtkMRMLSegmentationNode

    #
    # GuidewireReconstructionWidget
    #

    class GuidewireReconstructionWidget(ScriptedLoadableModuleWidget, VTKObservationMixin):
        """Thin widget: binds the parameter node, enables the buttons, calls the Logic."""

        def __init__(self, parent=None) -> None:
            ScriptedLoadableModuleWidget.__init__(self, parent)
            VTKObservationMixin.__init__(self)
            self.logic = None
            self._parameterNode = None
            self._parameterNodeGuiTag = None

        def setup(self) -> None:
            ScriptedLoadableModuleWidget.setup(self)
            uiWidget = slicer.util.loadUI(self.resourcePath("UI/GuidewireReconstruction.ui"))
            self.layout.addWidget(uiWidget)
            self.ui = slicer.util.childWidgetVariables(uiWidget)
            uiWidget.setMRMLScene(slicer.mrmlScene)
            self.logic = GuidewireReconstructionLogic()

            self.addObserver(slicer.mrmlScene, slicer.mrmlScene.StartCloseEvent, self.onSceneStartClose)
            self.addObserver(slicer.mrmlScene, slicer.mrmlScene.EndCloseEvent, self.onSceneEndClose)
            self.ui.installButton.connect("clicked(bool)", self.onInstallButton)
            self.ui.applyButton.connect("clicked(bool)", self.onApplyButton)
            self.ui.extractVesselsButton.connect("clicked(bool)", self.onExtractVesselsButton)
            self.ui.refineButton.connect("clicked(bool)", self.onRefineButton)
            self.ui.adjustButton.connect("toggled(bool)", self.onAdjustToggled)
            self.ui.saveButton.connect("clicked(bool)", self.onSaveButton)
            self._setupLive()
            self.initializeParameterNode()

        def _setupLive(self) -> None:
            """The "Live" section: follow a `guidewire3d live` server (HOST:PORT); a timer polls it."""
            box = ctk.ctkCollapsibleButton()
            box.text = _("Live")
            box.collapsed = True
            form = qt.QFormLayout(box)
            self.liveAddress = qt.QLineEdit("127.0.0.1:18944")
            self.liveAddress.toolTip = _("HOST:PORT of a running `guidewire3d live` server")
            form.addRow(_("Server:"), self.liveAddress)
            self.liveButton = qt.QPushButton(_("Connect"))
            self.liveButton.checkable = True
            self.liveButton.connect("toggled(bool)", self.onLiveToggled)
            form.addRow(self.liveButton)
            self.liveLabel = qt.QLabel(_("not connected"))
            self.liveLabel.wordWrap = True
            form.addRow(self.liveLabel)
            self.layout.addWidget(box)
            self.liveTimer = qt.QTimer()
            self.liveTimer.setInterval(50)
            self.liveTimer.connect("timeout()", self.onLiveTick)

        def onLiveToggled(self, on: bool) -> None:
            self.liveTimer.stop()
            if not on:
                self.logic.core.disconnect_live()
                self.liveButton.text = _("Connect")
                self.liveLabel.text = _("not connected")
                return
            with slicer.util.tryWithErrorDisplay(_("Cannot connect to the live server."), waitCursor=True):
                self.logic.core.connect_live(self.liveAddress.text)
                self.liveButton.text = _("Disconnect")
                self.liveLabel.text = self.logic.core.live_status
                self.liveTimer.start()
                return
            self.liveButton.checked = False

        def onLiveTick(self) -> None:
            self.logic.core.poll_live()
            self.liveLabel.text = self.logic.core.live_status

        def cleanup(self) -> None:
            self.liveTimer.stop()
            if self.logic is not None and self.logic._core is not None:
                self.logic._core.disconnect_live()
            self.removeObservers()

        def enter(self) -> None:
            self.initializeParameterNode()

        def exit(self) -> None:
            if self._parameterNode:
                self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
                self._parameterNodeGuiTag = None
                self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)

        def onSceneStartClose(self, caller, event) -> None:
            self.setParameterNode(None)
            self.logic.reset()  # its output nodes are about to be removed

        def onSceneEndClose(self, caller, event) -> None:
            if self.parent.isEntered:
                self.initializeParameterNode()

        def initializeParameterNode(self) -> None:
            self.setParameterNode(self.logic.getParameterNode())
            if not self._parameterNode.ctaVolume:
                first = slicer.mrmlScene.GetFirstNodeByClass("vtkMRMLScalarVolumeNode")
                if first:
                    self._parameterNode.ctaVolume = first

        def setParameterNode(self, inputParameterNode) -> None:
            if self._parameterNode:
                self._parameterNode.disconnectGui(self._parameterNodeGuiTag)
                self.removeObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
            self._parameterNode = inputParameterNode
            if self._parameterNode:
                # widgets carry a "SlicerParameterName" dynamic property in the .ui file
                self._parameterNodeGuiTag = self._parameterNode.connectGui(self.ui)
                self.addObserver(self._parameterNode, vtk.vtkCommand.ModifiedEvent, self._checkCanApply)
            self._checkCanApply()

        def _checkCanApply(self, caller=None, event=None) -> None:
            p = self._parameterNode
            installed = self.logic.dependenciesInstalled()
            self.ui.installButton.visible = not installed
            ready = bool(p and p.ctaVolume and (p.roadmapSequence or _path_or_none(p.roadmapPath)))
            self.ui.applyButton.enabled = installed and ready
            self.ui.applyButton.toolTip = _("Run the reconstruction") if ready else _("Select the CTA and the XA roadmap")
            has_cta = bool(p and p.ctaVolume)
            self.ui.extractVesselsButton.enabled = installed and has_cta
            self.ui.extractVesselsButton.toolTip = (_("Extract the vessel trees of the CTA (no X-ray needed)") if has_cta
                                                    else _("Select the CTA"))
            has_result = self.logic.hasResult()
            self.ui.refineButton.enabled = has_result
            self.ui.adjustButton.enabled = has_result
            self.ui.saveButton.enabled = has_result or self.logic.hasVessels()

        def onInstallButton(self) -> None:
            with slicer.util.tryWithErrorDisplay(_("Failed to install guidewire3d."), waitCursor=True):
                ensureDependencies()
            self._checkCanApply()

        def onApplyButton(self) -> None:
            with slicer.util.tryWithErrorDisplay(_("Reconstruction failed."), waitCursor=True):
                self.ui.statusLabel.text = self.logic.process(self._parameterNode)
            self._checkCanApply()

        def onExtractVesselsButton(self) -> None:
            with slicer.util.tryWithErrorDisplay(_("Vessel extraction failed."), waitCursor=True):
                self.ui.statusLabel.text = self.logic.extractVessels(self._parameterNode)
            self._checkCanApply()

        def onRefineButton(self) -> None:
            with slicer.util.tryWithErrorDisplay(_("Refinement failed."), waitCursor=True):
                self.ui.statusLabel.text = self.logic.refine(self._parameterNode)

        def onAdjustToggled(self, on: bool) -> None:
            with slicer.util.tryWithErrorDisplay(_("Cannot show the transform handles.")):
                self.logic.setTransformInteraction(self._parameterNode, on)

        def onSaveButton(self) -> None:
            directory = qt.QFileDialog.getExistingDirectory(None, _("Save outputs to folder"))
            if not directory:
                return
            with slicer.util.tryWithErrorDisplay(_("Saving failed."), waitCursor=True):
                paths = self.logic.core.save_outputs(directory)
                self.ui.statusLabel.text = _("Saved {n} files to {d}").format(n=len(paths), d=directory)

    #
    # GuidewireReconstructionLogic
    #

    class GuidewireReconstructionLogic(ScriptedLoadableModuleLogic):
        """Maps the parameter node onto ``GuidewireReconstructionCoreLogic`` (no GUI calls)."""

        def __init__(self) -> None:
            ScriptedLoadableModuleLogic.__init__(self)
            self._core = None

        def getParameterNode(self):
            return GuidewireReconstructionParameterNode(super().getParameterNode())

        @staticmethod
        def dependenciesInstalled() -> bool:
            return _importable()

        @property
        def core(self):
            if self._core is None or self._core.scene is not slicer.mrmlScene:
                app = getattr(slicer, "app", None)
                self._core = coreLogicClass()(slicer.mrmlScene, app_logic=app.applicationLogic() if app else None)
            return self._core

        def hasResult(self) -> bool:
            return self._core is not None and self._core.result is not None

        def hasVessels(self) -> bool:
            """True after "Extract vessels" (its nodes can be saved)."""
            return self._core is not None and self._core.plan is not None

        def reset(self) -> None:
            """Forget the last result and its output nodes (the scene is being closed)."""
            self._core = None

        def process(self, parameterNode) -> str:
            """Run the reconstruction with the parameters of ``parameterNode``; returns a summary line."""
            return self.core.process_parameters(parameterNode)

        def extractVessels(self, parameterNode) -> str:
            """Extract the vessel trees of the CTA alone (planning; no X-ray); returns the summary."""
            return self.core.plan_vessels_parameters(parameterNode)

        def refine(self, parameterNode) -> str:
            """Refine from the (user-corrected) registration transform; returns a summary line."""
            return self.core.refine_parameters(parameterNode)

        def setTransformInteraction(self, parameterNode, on: bool) -> None:
            self.core.set_transform_interaction(on, transform_node=parameterNode.registrationTransform)

    #
    # GuidewireReconstructionTest
    #

    class GuidewireReconstructionTest(ScriptedLoadableModuleTest):
        """Runs the module on a simulated case inside Slicer and asserts the numbers."""

        #: the accuracy the tests require (issue 7's 3D tolerance); see tests/test_plugin.py
        MEAN_ERROR_MM = 0.7

        def setUp(self):
            slicer.mrmlScene.Clear()

        def runTest(self):
            self.assertTrue(ensureDependencies(), "guidewire3d could not be installed")
            self.setUp()
            self.test_reconstruction_matches_truth()
            self.setUp()
            self.test_bad_input_raises()

        def _case(self):
            import tempfile

            from guidewire3d import phantom

            self._tmp = tempfile.TemporaryDirectory()
            case = phantom.simulate(phantom.PhantomOptions(seed=3, n_frames=4))  # = tests/conftest.py small_case
            case_dir = phantom.write_case(case, Path(self._tmp.name) / "case")
            return phantom.load_truth(case_dir), case_dir

        def test_reconstruction_matches_truth(self):
            import numpy as np

            from guidewire3d import metrics
            from GuidewireReconstructionLib.logic import lps_to_ras, pose_from_transform_node

            self.delayDisplay("Simulating a case")
            truth, case_dir = self._case()
            first = sorted((case_dir / "ct").iterdir())[0]
            cta = slicer.util.loadVolume(str(first), {"singleFile": False})
            logic = GuidewireReconstructionLogic()
            p = logic.getParameterNode()
            p.ctaVolume = cta
            p.roadmapPath = case_dir / "roadmap.dcm"
            p.framesPath = case_dir / "frames.dcm"
            p.segmenter = "ridge"  # the configuration tests/test_plugin.py checks (no trained weights needed)
            self.delayDisplay("Running the reconstruction")
            logic.process(p)
            core = logic.core
            # the transform node holds the registration pose in RAS
            T = slicer.util.arrayFromTransformMatrix(p.registrationTransform, toWorld=False)
            np.testing.assert_allclose(np.linalg.inv(T), lps_to_ras(core.registration.pose.matrix), atol=1e-6)
            self.assertTrue(pose_from_transform_node(p.registrationTransform).allclose(core.registration.pose, atol_mm=1e-6))
            # every reconstructed wire (curve node, RAS) agrees with the truth converted to RAS
            errors = []
            for curve, fid in zip(core.outputs.wire_curves, core.outputs.frame_indices):
                if curve.GetNumberOfControlPoints() < 2:
                    continue
                est_ras = slicer.util.arrayFromMarkupsControlPoints(curve)
                vis = np.asarray(truth.wire_visible[fid], bool)
                truth_ras = lps_to_ras(np.asarray(truth.wire_lps_mm[fid])[vis])
                errors.append(metrics.wire_errors_mm(est_ras, truth_ras)["mean_error_mm"])
            self.assertEqual(len(errors), truth.n_frames)  # every frame reconstructed
            self.assertLessEqual(float(np.mean(errors)), self.MEAN_ERROR_MM)
            self.assertEqual(p.metricsTable.GetNumberOfRows(), len(core.wires3d))
            self.delayDisplay(f"Mean 3D wire error {np.mean(errors):.2f} mm over {len(errors)} frames")

            # outputs save and reload through their storage nodes
            paths = core.save_outputs(Path(self._tmp.name) / "out")
            curve = core.outputs.wire_curves[-1]
            saved = next(q for q in paths if q.name.startswith(curve.GetName().replace(" ", "_")))
            back = slicer.util.loadMarkups(str(saved))
            np.testing.assert_allclose(slicer.util.arrayFromMarkupsControlPoints(back),
                                       slicer.util.arrayFromMarkupsControlPoints(curve), atol=1e-4)

            # Refine after the user moved the C-arm: the vessels project back where the registration put them
            from guidewire3d.geometry import Pose
            from GuidewireReconstructionLib.logic import pose_to_transform_node

            auto = core.registration.pose
            pts = truth.tree.points_lps_mm
            carm = core.result.carm
            offset = lambda a, b: float(np.linalg.norm(carm.project(pts, a) - carm.project(pts, b), axis=1).mean())  # noqa: E731
            moved = Pose.exp([3.0, -2.0, 1.5, *np.radians([2.0, -1.0, 1.0])]) @ auto
            pose_to_transform_node(moved, p.registrationTransform)
            logic.refine(p)
            self.assertTrue(core.registration.success)
            self.assertLess(offset(core.registration.pose, auto), 0.25 * offset(moved, auto))
            self.delayDisplay("Refine brought the moved C-arm back")

        def test_bad_input_raises(self):
            from guidewire3d.errors import InputError

            logic = GuidewireReconstructionLogic()
            p = logic.getParameterNode()
            with self.assertRaisesRegex(InputError, "roadmap"):
                logic.process(p)  # no roadmap
            p.roadmapPath = Path(slicer.app.temporaryPath) / "does-not-exist.dcm"
            with self.assertRaisesRegex(InputError, "no such file"):
                logic.process(p)
