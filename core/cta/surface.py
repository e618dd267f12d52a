"""CTA vessels, stage 2: the surface mesh of the vessel mask.

:func:`surface_from_mask` - VTK discrete flying edges, windowed-sinc smoothing, decimation and
normals; a closed triangle mesh in LPS mm ready for VTP/STL export.
"""
from __future__ import annotations

import numpy as np
from guidewire3d.cta.grid import affine_zyx, bbox, check_grid
from guidewire3d.errors import InputError, SegmentationError

__all__ = ["surface_from_mask"]


def surface_from_mask(mask_zyx, *, spacing_mm, origin_lps_mm, direction=None, smooth_iterations: int = 20,
                      decimate: float = 0.5):
    """Closed triangle mesh of a mask, in LPS mm.

    Parameters
    ----------
    mask_zyx : (z, y, x) array_like of bool
    spacing_mm, origin_lps_mm : (3,) float, ``(x, y, z)``
    direction : (3, 3) array_like, optional
        Columns are the x, y, z index axes in LPS (identity when omitted).
    smooth_iterations : int
        Windowed-sinc smoothing iterations (0 = none).
    decimate : float
        Fraction of triangles to remove (0 = none), topology preserved.

    Returns
    -------
    vtk.vtkPolyData
        Triangles with outward point normals (``Normals``), LPS mm.
    """
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    m, sp = check_grid(mask_zyx, spacing_mm, origin_lps_mm, direction, "surface_from_mask")
    if not m.any():
        raise SegmentationError("surface_from_mask: no vessels found (the mask is empty)")
    if not 0 <= decimate < 1:
        raise InputError(f"surface_from_mask: decimate must be in [0, 1), got {decimate}")
    sl = bbox(m, pad=1)
    off = np.array([s.start for s in sl], dtype=float)
    sub = np.pad(m[sl], 1).astype(np.uint8)
    off -= 1
    img = vtk.vtkImageData()
    img.SetDimensions(sub.shape[2], sub.shape[1], sub.shape[0])
    img.SetSpacing(1.0, 1.0, 1.0)
    img.SetOrigin(0.0, 0.0, 0.0)
    arr = numpy_to_vtk(np.ascontiguousarray(sub).ravel(), deep=True, array_type=vtk.VTK_UNSIGNED_CHAR)
    img.GetPointData().SetScalars(arr)
    fe = vtk.vtkDiscreteFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 1)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.Update()
    poly = fe.GetOutput()
    if smooth_iterations > 0:
        ws = vtk.vtkWindowedSincPolyDataFilter()
        ws.SetInputData(poly)
        ws.SetNumberOfIterations(int(smooth_iterations))
        ws.SetPassBand(0.05)
        ws.BoundarySmoothingOff()
        ws.FeatureEdgeSmoothingOff()
        ws.NonManifoldSmoothingOn()
        ws.NormalizeCoordinatesOn()
        ws.Update()
        poly = ws.GetOutput()
    if decimate > 0:
        dec = vtk.vtkQuadricDecimation()
        dec.SetInputData(poly)
        dec.SetTargetReduction(float(decimate))
        dec.VolumePreservationOn()
        dec.Update()
        poly = dec.GetOutput()
    # index (x, y, z) of the padded crop -> LPS
    M, o = affine_zyx(sp, origin_lps_mm, direction)  # acts on (z, y, x)
    Mx = M[:, ::-1]  # acts on (x, y, z)
    ox = o + M @ off
    T = vtk.vtkMatrix4x4()
    for i in range(3):
        for j in range(3):
            T.SetElement(i, j, float(Mx[i, j]))
        T.SetElement(i, 3, float(ox[i]))
    tr = vtk.vtkTransform()
    tr.SetMatrix(T)
    tf = vtk.vtkTransformPolyDataFilter()
    tf.SetInputData(poly)
    tf.SetTransform(tr)
    tf.Update()
    nrm = vtk.vtkPolyDataNormals()
    nrm.SetInputData(tf.GetOutput())
    nrm.ComputePointNormalsOn()
    nrm.ComputeCellNormalsOff()
    nrm.SplittingOff()
    nrm.ConsistencyOn()
    nrm.AutoOrientNormalsOn()
    nrm.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(nrm.GetOutput())
    return out
