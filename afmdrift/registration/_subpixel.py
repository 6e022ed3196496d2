"""Compiled sub-pixel step of the block pass (Numba, no GIL): the continuous
maximum of the band-limited correlation (``dft``, the default), or a
three-point peak model (``sinc``, ``parabolic``, ``gaussian``).
"""

from __future__ import annotations

import math

import numpy as np

from afmdrift.registration._jit import jit, jit_sums

__all__ = ["SUBPIXEL_CODES", "dft_subpixel", "subpixel_3pt"]

#: Newton iterations of the ``dft`` sub-pixel method after the quadratic start
#: (quadratic convergence: the second step checks that the first converged).
NEWTON_STEPS = 2
#: Largest Newton step (px) and the last step below which it has converged.
MAX_STEP_PX = 1.0
CONVERGED_PX = 0.02

#: ``method`` codes of :func:`subpixel_3pt` (``config.subpixel``; ``dft`` is 0).
SUBPIXEL_CODES = {"dft": 0, "sinc": 1, "parabolic": 2, "gaussian": 3}


@jit
def _ascent_step(gx, gy, hxx, hyy, hxy):  # type: ignore[no-untyped-def]
    """Newton step towards a maximum where the Hessian is negative definite,
    else a unit gradient-ascent step; both bounded by ``MAX_STEP_PX``."""
    det = hxx * hyy - hxy * hxy
    if hxx < 0 and det > 0:
        sx = -(hyy * gx - hxy * gy) / det
        sy = -(hxx * gy - hxy * gx) / det
    else:
        sx = np.sign(gx)
        sy = np.sign(gy)
    return (
        min(max(sx, -MAX_STEP_PX), MAX_STEP_PX),
        min(max(sy, -MAX_STEP_PX), MAX_STEP_PX),
    )


@jit_sums
def _phases(f, d, out_re, out_im):  # type: ignore[no-untyped-def]
    """``out = exp(2πi f[j] d)`` (real and imaginary parts) for evenly spaced
    frequencies ``f`` (a geometric sequence: two complex exponentials, then
    products)."""
    z = np.exp(2j * math.pi * f[0] * d)
    step = np.exp(2j * math.pi * (f[1] - f[0]) * d)
    for j in range(f.size):
        out_re[j] = z.real
        out_im[j] = z.imag
        z *= step


@jit_sums
def dft_subpixel(c, blocks, band, peaks):  # type: ignore[no-untyped-def]
    """Continuous maximum of the band-limited correlation, per block.

    ``c(p) = Re Σ_k w_k R_k exp(2πi k·p)`` over the band ``R`` (interleaved
    complex; rows at the evenly spaced frequencies ``c.fy``, columns at
    ``c.fx = 0, 1/E, ...`` with Hermitian weight 2 for ``fx > 0``), centred
    on the integer peak ``(sy, sx)``. A quadratic through ``c`` at the best
    of the 5×5 integer offsets around the peak starts :data:`NEWTON_STEPS`
    Newton steps with the analytic gradient and Hessian of ``log c``, which
    also divide out the window autocorrelation
    ``A(p) ≈ exp(-κx px²/2 - κy py²/2)`` (``c.envelope = (κy, κx)``).

    For a pure translation ``R_k = A_k exp(-2πi k·d)`` with ``A_k ≥ 0``
    symmetric in ``k``, so the maximum lies exactly at ``d`` whatever the
    texture's spectrum: no peak-shape model, no pixel-locking bias.

    ``c``: :class:`~afmdrift.registration._constants.SubpixelConstants`;
    ``c.shift = (my, mx)`` is the shift the reference's phase ramp put into
    the band (see :func:`afmdrift.registration._spectra.normalise_reference`;
    zeros for none).

    ``band[k]`` belongs to block ``blocks[k]``, the index of ``peaks`` (a
    :class:`~afmdrift.registration._passes.Peaks`), whose integer peaks
    ``sy``, ``sx`` are read. Writes the offsets from the integer peak
    (``fx``, ``fy``) and whether the iteration converged within 3 px of it
    (``ok``; offsets 0 where it did not).
    """
    ly, lx = band.shape[1], c.fx.size
    # Complex values as separate real and imaginary float64 arrays: the
    # sums over the band then compile to packed arithmetic.
    r0 = (np.empty((ly, lx)), np.empty((ly, lx)))
    phases = (np.empty(lx), np.empty(lx), np.empty(ly), np.empty(ly))
    c5 = np.empty((5, 5))
    fx2 = c.fx * c.fx
    # exp(2πi f·o) at the integer offsets o = -2..2 (the same for every
    # block), and scratch for the sums over them.
    grid = (
        np.empty((5, lx)),
        np.empty((5, lx)),
        np.empty((5, ly)),
        np.empty((5, ly)),
        np.empty((5, ly)),
        np.empty((5, ly)),
    )
    for o in range(5):
        _phases(c.fx, o - 2.0, grid[0][o], grid[1][o])
        _phases(c.fy, o - 2.0, grid[2][o], grid[3][o])
    for k in range(blocks.size):
        i = blocks[k]
        sy, sx = peaks.sy[i], peaks.sx[i]
        _centred_band(c, band[k], float(sy + c.shift[0]), float(sx + c.shift[1]), phases, r0)
        _integer_grid(r0, grid, c5)
        dx, dy = _quadratic_start(c5)
        dx, dy, step = _newton(c, fx2, r0, phases, dx, dy, sx, sy)
        ok = step < CONVERGED_PX and abs(dx) <= 3.0 and abs(dy) <= 3.0
        peaks.ok[i] = ok
        peaks.fx[i] = dx if ok else 0.0
        peaks.fy[i] = dy if ok else 0.0


@jit_sums
def _centred_band(c, band, sy, sx, phases, r0):  # type: ignore[no-untyped-def]
    """``r0 = w · R · exp(2πi k·s)`` (real and imaginary parts): one block's
    band ``R`` centred on its peak ``s = (sy, sx)`` in the band, with the
    Hermitian weight ``w`` (2 for ``fx > 0``); ``phases``: scratch."""
    px_re, px_im, py_re, py_im = phases
    r0_re, r0_im = r0
    ly, lx = r0_re.shape
    _phases(c.fx, sx, px_re, px_im)
    _phases(c.fy, sy, py_re, py_im)
    for x in range(1, lx):
        px_re[x] *= 2.0
        px_im[x] *= 2.0
    for y in range(ly):
        a_re, a_im = py_re[y], py_im[y]
        for x in range(lx):
            b_re = np.float64(band[y, 2 * x])
            b_im = np.float64(band[y, 2 * x + 1])
            u_re = b_re * a_re - b_im * a_im
            u_im = b_re * a_im + b_im * a_re
            r0_re[y, x] = u_re * px_re[x] - u_im * px_im[x]
            r0_im[y, x] = u_re * px_im[x] + u_im * px_re[x]


@jit_sums
def _integer_grid(r0, grid, c5):  # type: ignore[no-untyped-def]
    """``c5[a, b]``: the correlation at the integer offsets ``(a - 2, b - 2)``
    from the centred band ``r0`` (separable sums; ``grid``: the phases at
    those offsets along x and y, then scratch)."""
    r0_re, r0_im = r0
    ex5_re, ex5_im, ey5_re, ey5_im, t5_re, t5_im = grid
    ly, lx = r0_re.shape
    for y in range(ly):
        for b in range(5):
            s_re = 0.0
            s_im = 0.0
            for x in range(lx):
                s_re += r0_re[y, x] * ex5_re[b, x] - r0_im[y, x] * ex5_im[b, x]
                s_im += r0_re[y, x] * ex5_im[b, x] + r0_im[y, x] * ex5_re[b, x]
            t5_re[b, y] = s_re
            t5_im[b, y] = s_im
    for a in range(5):
        for b in range(5):
            acc = 0.0
            for y in range(ly):
                acc += t5_re[b, y] * ey5_re[a, y] - t5_im[b, y] * ey5_im[a, y]
            c5[a, b] = acc


@jit_sums
def _quadratic_start(c5):  # type: ignore[no-untyped-def]
    """Start ``(dx, dy)`` of the Newton steps: a quadratic through the best
    of the 5×5 integer samples ``c5`` (kept off the edge) and its neighbours."""
    ba = 0
    bb = 0
    for a in range(5):
        for b in range(5):
            if c5[a, b] > c5[ba, bb]:
                ba, bb = a, b
    ba = min(max(ba, 1), 3)
    bb = min(max(bb, 1), 3)
    gx = 0.5 * (c5[ba, bb + 1] - c5[ba, bb - 1])
    gy = 0.5 * (c5[ba + 1, bb] - c5[ba - 1, bb])
    hxx = c5[ba, bb + 1] - 2.0 * c5[ba, bb] + c5[ba, bb - 1]
    hyy = c5[ba + 1, bb] - 2.0 * c5[ba, bb] + c5[ba - 1, bb]
    hxy = 0.25 * (c5[ba + 1, bb + 1] - c5[ba + 1, bb - 1] - c5[ba - 1, bb + 1] + c5[ba - 1, bb - 1])
    qx, qy = _ascent_step(gx, gy, hxx, hyy, hxy)
    return qx + (bb - 2), qy + (ba - 2)


@jit_sums
def _newton(c, fx2, r0, phases, dx, dy, sx, sy):  # type: ignore[no-untyped-def]
    """:data:`NEWTON_STEPS` Newton steps from ``(dx, dy)`` on ``log c`` of
    the centred band ``r0``, the window autocorrelation of a block whose
    integer peak is ``(sx, sy)`` divided out (``fx2``: ``c.fx²``;
    ``phases``: scratch). Returns the offsets and the last step's length
    (inf where ``c`` was not positive)."""
    fx, fy = c.fx, c.fy
    k_y, k_x = c.envelope[0], c.envelope[1]
    two_pi = 2.0 * math.pi
    px_re, px_im, py_re, py_im = phases
    r0_re, r0_im = r0
    ly, lx = r0_re.shape
    step = np.inf
    for _ in range(NEWTON_STEPS):
        _phases(fx, dx, px_re, px_im)
        _phases(fy, dy, py_re, py_im)
        # Σ z, Σ z fx, Σ z fx², Σ z fy, Σ z fx fy, Σ z fy² (the parts used)
        m00_re = 0.0
        m10_im = 0.0
        m20_re = 0.0
        m01_im = 0.0
        m11_re = 0.0
        m02_re = 0.0
        for y in range(ly):
            t0_re = 0.0
            t0_im = 0.0
            t1_re = 0.0
            t1_im = 0.0
            t2_re = 0.0
            t2_im = 0.0
            for x in range(lx):
                z_re = r0_re[y, x] * px_re[x] - r0_im[y, x] * px_im[x]
                z_im = r0_re[y, x] * px_im[x] + r0_im[y, x] * px_re[x]
                t0_re += z_re
                t0_im += z_im
                t1_re += z_re * fx[x]
                t1_im += z_im * fx[x]
                t2_re += z_re * fx2[x]
                t2_im += z_im * fx2[x]
            e_re, e_im = py_re[y], py_im[y]
            u0_re = t0_re * e_re - t0_im * e_im
            u0_im = t0_re * e_im + t0_im * e_re
            m00_re += u0_re
            m10_im += t1_re * e_im + t1_im * e_re
            m20_re += t2_re * e_re - t2_im * e_im
            m01_im += u0_im * fy[y]
            m11_re += (t1_re * e_re - t1_im * e_im) * fy[y]
            m02_re += u0_re * (fy[y] * fy[y])
        c0 = m00_re
        if c0 > 0:
            inv = 1.0 / c0
            gx = -two_pi * m10_im * inv
            gy = -two_pi * m01_im * inv
            hxx = -(two_pi**2) * m20_re * inv - gx * gx + k_x
            hyy = -(two_pi**2) * m02_re * inv - gy * gy + k_y
            hxy = -(two_pi**2) * m11_re * inv - gx * gy
            st_x, st_y = _ascent_step(gx + k_x * (sx + dx), gy + k_y * (sy + dy), hxx, hyy, hxy)
            dx += st_x
            dy += st_y
            step = math.hypot(st_x, st_y)
        else:
            step = np.inf
    return dx, dy, step


@jit
def _three_point(cm, c0, cp, method):  # type: ignore[no-untyped-def]
    """Sub-pixel offset of a peak from its samples left, centre and right
    (``method``: 1 sinc, 2 parabolic, 3 gaussian), and whether it is usable.

    sinc: Foroosh, Zerubia & Berthod (2002): the phase-correlation peak of a
    sub-pixel shift is a Dirichlet kernel, so a side sample over its sum with
    the centre gives the offset. parabolic and gaussian: the vertex of a
    parabola through the samples (gaussian: through their logarithms)."""
    off = 0.0
    if method == 1:
        right = cp >= cm
        side = cp if right else cm
        if side > 0:
            off = side / (side + c0)
        if not right:
            off = -off
    elif method == 2:
        den = cm - 2.0 * c0 + cp
        if den < 0:
            off = 0.5 * (cm - cp) / den
    else:
        lm = math.log(max(cm, 1e-12))
        l0 = math.log(max(c0, 1e-12))
        lp = math.log(max(cp, 1e-12))
        den = lm - 2.0 * l0 + lp
        if den < 0:
            off = 0.5 * (lm - lp) / den
    ok = math.isfinite(off) and abs(off) <= 1.0 and c0 > 0
    return (off if ok else 0.0), ok


@jit
def subpixel_3pt(c, blocks, corr, peaks):  # type: ignore[no-untyped-def]
    """Sub-pixel offsets of each block's integer peak ``(peaks.sy,
    peaks.sx)`` from the three samples around it along each axis
    (:func:`_three_point`, ``c.method``), in the shifted correlation
    ``corr`` (shift ``-c.shift`` at index 0; ``c.scale``: its value for
    identical blocks; ``corr[k]`` belongs to block ``blocks[k]``, the index
    of ``peaks``), into ``peaks.fy``, ``peaks.fx`` and ``peaks.ok``.
    Neighbours beyond ``0..2m`` are clamped. ``c``:
    :class:`~afmdrift.registration._constants.SubpixelConstants`."""
    method, scale = c.method, c.scale
    my, mx = c.shift[0], c.shift[1]
    for k in range(blocks.size):
        i = blocks[k]
        cy = peaks.sy[i] + my
        cx = peaks.sx[i] + mx
        ym, yp = max(cy - 1, 0), min(cy + 1, 2 * my)
        xm, xp = max(cx - 1, 0), min(cx + 1, 2 * mx)
        c0 = np.float64(corr[k, cy, cx]) / scale
        fy, ok_y = _three_point(
            np.float64(corr[k, ym, cx]) / scale, c0, np.float64(corr[k, yp, cx]) / scale, method
        )
        fx, ok_x = _three_point(
            np.float64(corr[k, cy, xm]) / scale, c0, np.float64(corr[k, cy, xp]) / scale, method
        )
        peaks.fy[i] = fy
        peaks.fx[i] = fx
        peaks.ok[i] = ok_x and ok_y
