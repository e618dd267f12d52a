"""Compiled kernels of the live path (numba): the loops that numpy cannot vectorise.

The per-frame engine (:class:`guidewire3d.live.session.Session`) spends its time in a few loops over small
arrays: the Viterbi recursion of the 3D reconstruction (one step per anchor of the 2D wire) and the
bilinear sampling of profiles across the 2D wire (sub-pixel centring, end caps, the presence test).
Each kernel here computes what the numpy / SciPy code it replaces computes, in the same order of
floating-point operations where that is possible (the tests compare them on random inputs).

numba is imported on the first call of a kernel, not when this module is imported, so that
``import guidewire3d`` stays light; the compiled code is cached on disk (``cache=True``) and
:func:`warm_up` compiles (or loads) every kernel ahead of the first frame.
"""
from __future__ import annotations

import threading
import warnings

import numpy as np

__all__ = ["viterbi_forward", "viterbi_backward", "sample_bilinear", "warm_up"]

_LOCK = threading.Lock()
#: image dtypes sampled as they are (one compiled specialisation each); others are converted to float64
_DIRECT = tuple(np.dtype(t) for t in (np.float64, np.float32, np.uint8, np.uint16, np.int16, np.int32, np.int64))
_WARM = (np.float64, np.float32, np.uint8, np.uint16)
_COMPILED: dict = {}


def _compile():
    """The jitted functions (compiled once per process; loaded from numba's disk cache when present)."""
    with _LOCK:
        if _COMPILED:
            return _COMPILED
        import numba

        def jit(f):
            try:  # cached on disk beside the module, or in the user's cache folder
                return numba.njit(cache=True, nogil=True)(f)
            except RuntimeError:  # no writable cache location: compiled in memory, once per process
                return numba.njit(cache=False, nogil=True)(f)

        @jit
        def viterbi_forward(acc0, U, C, skip_cost):
            A, K = U.shape
            alpha = np.empty((A, K))
            back = np.zeros((max(A - 1, 0), K), np.int64)
            acc = acc0.copy()
            alpha[0] = acc
            end_t = 0
            end_k = 0
            for k in range(1, K):
                if acc[k] < acc[end_k]:
                    end_k = k
            end_cost = acc[end_k] + skip_cost * (A - 1)
            new = np.empty(K)
            for t in range(A - 1):
                for j in range(K):
                    bi = 0
                    best = acc[0] + C[t, 0, j]
                    for i in range(1, K):
                        v = acc[i] + C[t, i, j]
                        if v < best:
                            best = v
                            bi = i
                    back[t, j] = bi
                    new[j] = best + U[t + 1, j]
                k = 0
                for j in range(K):
                    acc[j] = new[j]
                    alpha[t + 1, j] = new[j]
                    if new[j] < new[k]:
                        k = j
                c = acc[k] + skip_cost * (A - 2 - t)
                if c < end_cost:
                    end_t, end_k, end_cost = t + 1, k, c
            return alpha, back, end_t, end_k, end_cost

        @jit
        def viterbi_backward(C, U, end_t):
            K = U.shape[1]
            beta = np.zeros((end_t + 1, K))
            w = np.empty(K)
            for t in range(end_t - 1, -1, -1):
                for j in range(K):
                    w[j] = U[t + 1, j] + beta[t + 1, j]
                for i in range(K):
                    m = C[t, i, 0] + w[0]
                    for j in range(1, K):
                        v = C[t, i, j] + w[j]
                        if v < m:
                            m = v
                    beta[t, i] = m
            return beta

        @jit
        def sample_bilinear(img, rows, cols, nearest, cval):
            H, W = img.shape
            n = rows.shape[0]
            out = np.empty(n)
            for k in range(n):
                r = rows[k]
                c = cols[k]
                if nearest:
                    r = min(max(r, 0.0), H - 1.0)
                    c = min(max(c, 0.0), W - 1.0)
                elif not (r >= 0.0 and r <= H - 1.0 and c >= 0.0 and c <= W - 1.0):
                    out[k] = cval
                    continue
                r0 = int(np.floor(r))
                c0 = int(np.floor(c))
                tr = r - r0
                tc = c - c0
                r1 = min(r0 + 1, H - 1)
                c1 = min(c0 + 1, W - 1)
                # SciPy's order: the sum over the 2 x 2 neighbours of (value * row weight) * col weight
                t = 0.0
                t += (img[r0, c0] * (1.0 - tr)) * (1.0 - tc)
                t += (img[r0, c1] * (1.0 - tr)) * tc
                t += (img[r1, c0] * tr) * (1.0 - tc)
                t += (img[r1, c1] * tr) * tc
                out[k] = t
            return out

        _COMPILED.update(viterbi_forward=viterbi_forward, viterbi_backward=viterbi_backward,
                         sample_bilinear=sample_bilinear)
        return _COMPILED


def viterbi_forward(acc0: np.ndarray, U: np.ndarray, C: np.ndarray, skip_cost: float):
    """Min-sum forward pass of the reconstruction's Viterbi with an early end.

    Parameters
    ----------
    acc0 : (K,) ndarray of float
        Cost of each candidate of the first anchor.
    U : (A, K) ndarray of float
        Unary costs (``inf`` where there is no candidate).
    C : (A - 1, K, K) ndarray of float
        Pairwise costs of step ``t``: candidate ``i`` of anchor ``t`` to ``j`` of anchor ``t + 1``.
    skip_cost : float
        Cost per anchor left unexplained when the path ends early.

    Returns
    -------
    alpha : (A, K) forward costs; back : (A - 1, K) int64 back-pointers (first minimum on ties,
    as ``numpy.argmin``); end_t, end_k : the best end; end_cost : its cost with the skipped anchors.
    """
    f = _compile()["viterbi_forward"]
    return f(np.ascontiguousarray(acc0, np.float64), np.ascontiguousarray(U, np.float64),
             np.ascontiguousarray(C, np.float64), float(skip_cost))


def viterbi_backward(C: np.ndarray, U: np.ndarray, end_t: int) -> np.ndarray:
    """Backward min-sum costs ``beta (end_t + 1, K)`` of the path ending at anchor ``end_t``:
    ``beta[t, i] = min_j C[t, i, j] + (U[t + 1, j] + beta[t + 1, j])``, ``beta[end_t] = 0``."""
    f = _compile()["viterbi_backward"]
    return f(np.ascontiguousarray(C, np.float64), np.ascontiguousarray(U, np.float64), int(end_t))


def sample_bilinear(image: np.ndarray, rows, cols, *, mode: str = "nearest", cval: float = 0.0) -> np.ndarray:
    """Bilinear samples of a 2D image at (row, col) points: ``scipy.ndimage.map_coordinates(image,
    [rows, cols], order=1, mode=mode, cval=cval)`` for ``mode`` "nearest" (coordinates clamped to
    the image) or "constant" (``cval`` outside ``[0, H - 1] x [0, W - 1]``), as float64.

    Parameters
    ----------
    image : (H, W) ndarray of a real or bool dtype (sampled without a float copy of the image)
    rows, cols : array_like of float, same shape
    """
    if mode not in ("nearest", "constant"):
        raise ValueError(f"sample_bilinear: mode must be 'nearest' or 'constant', got {mode!r}")
    img = np.asarray(image)
    if img.dtype == bool:
        img = img.view(np.uint8)
    elif img.dtype not in _DIRECT:
        img = img.astype(np.float64)
    r = np.asarray(rows, np.float64)
    shape = r.shape
    f = _compile()["sample_bilinear"]
    out = f(np.ascontiguousarray(img), np.ascontiguousarray(r.ravel()),
            np.ascontiguousarray(np.asarray(cols, np.float64).ravel()), mode == "nearest", float(cval))
    return out.reshape(shape)


def warm_up() -> None:
    """Compile (or load from the disk cache) every kernel on tiny inputs: the first live frame then
    pays no compilation."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba's cache-locator notes on a read-only install
        U = np.zeros((3, 2))
        C = np.zeros((2, 2, 2))
        viterbi_forward(U[0], U, C, 1.0)
        viterbi_backward(C, U, 2)
        for dt in _WARM:  # the masks and the usual frame dtypes (others compile on first use)
            sample_bilinear(np.zeros((3, 3), dt), [0.5], [0.5], mode="nearest")
