"""Stretching: the data-driven anisotropic model of Wang, Ramamoorthi and O'Brien 2011 as ARCSim evaluates it.

Formulas follow SPEC.md §1.2 (ARCSim ``physics.cpp`` stretching force and its PSD Hessian, ``dde.cpp`` table).
The stiffness table is never materialised: each of the 30^3 lookup cells is a fixed linear combination of three rows
of the 6x4 parameter table (``lut_weight``, ``lut_row``), so the per-face trilinear lookup reads the parameters
directly and Warp's autodiff carries gradients to them.
"""

import functools
from types import SimpleNamespace

import warp as wp

from warpcloth.kernels.types import types

LUT_SIZE = 30
"""Cells per axis of the stiffness lookup (ARCSim ``nsamples``)."""


@functools.cache
def stretching_funcs(scalar):
    t = types(scalar)
    vec3, vec4, mat22 = t.vec3, t.vec4, t.mat22
    N = LUT_SIZE
    cells = float(LUT_SIZE)  # float closures: scalar(int) does not cast in float64 code
    last = float(LUT_SIZE - 1)

    @wp.func
    def table_row(stretching: wp.array3d(dtype=scalar), material: int, row: int):
        return vec4(
            stretching[material, row, 0],
            stretching[material, row, 1],
            stretching[material, row, 2],
            stretching[material, row, 3],
        )

    @wp.func
    def cell_stiffness(stretching: wp.array3d(dtype=scalar), material: int, w: vec3, r: int):
        # One lookup cell (row weights w of table rows 0, r+1, r+2): bilinear sample of the (strain level x angle)
        # table, then relu(2 * value) (SPEC §1.2).
        value = (
            w[0] * table_row(stretching, material, 0)
            + w[1] * table_row(stretching, material, r + 1)
            + w[2] * table_row(stretching, material, r + 2)
        )
        zero = vec4(scalar(0.0), scalar(0.0), scalar(0.0), scalar(0.0))
        return wp.max(scalar(2.0) * value, zero)

    @wp.func
    def lut_coord(value: scalar):
        # align_corners=True with border clamping: index = value * N, clamped to [0, N-1]
        f = wp.clamp(value * scalar(cells), scalar(0.0), scalar(last))
        i = wp.min(int(wp.floor(f)), N - 2)
        return i, f - scalar(i)

    @wp.func
    def stiffness(
        stretching: wp.array3d(dtype=scalar),
        lut_weight: wp.array(dtype=vec3),
        lut_row: wp.array(dtype=wp.int32),
        material: int,
        G00: scalar,
        G11: scalar,
        G01: scalar,
    ):
        """Stiffness 4-vector (k0, k1, k2, k3) [N/m] before ``thicken``, trilinear in (G00, G11, |G01|)."""
        i, fi = lut_coord(G00 + scalar(0.25))
        j, fj = lut_coord(G11 + scalar(0.25))
        k, fk = lut_coord(wp.abs(G01))
        one = scalar(1.0)
        out = vec4(scalar(0.0), scalar(0.0), scalar(0.0), scalar(0.0))
        for di in range(2):
            wi = wp.where(di == 0, one - fi, fi)
            for dj in range(2):
                wj = wp.where(dj == 0, one - fj, fj)
                for dk in range(2):
                    wk = wp.where(dk == 0, one - fk, fk)
                    cell = ((i + di) * N + (j + dj)) * N + (k + dk)
                    out = out + (wi * wj * wk) * cell_stiffness(stretching, material, lut_weight[cell], lut_row[cell])
        return out

    @wp.func
    def shape_gradients(inv_dm: mat22):
        """Weights of x0, x1, x2 in the columns xu, xv of F (the Du, Dv operators of SPEC §1.2)."""
        du = vec3(-inv_dm[0, 0] - inv_dm[1, 0], inv_dm[0, 0], inv_dm[1, 0])
        dv = vec3(-inv_dm[0, 1] - inv_dm[1, 1], inv_dm[0, 1], inv_dm[1, 1])
        return du, dv

    @wp.func
    def deformation(x0: vec3, x1: vec3, x2: vec3, inv_dm: mat22):
        """Columns of F and the Green strain components G00, G11, G01."""
        du, dv = shape_gradients(inv_dm)
        xu = du[0] * x0 + du[1] * x1 + du[2] * x2
        xv = dv[0] * x0 + dv[1] * x1 + dv[2] * x2
        half = scalar(0.5)
        G00 = half * (wp.dot(xu, xu) - scalar(1.0))
        G11 = half * (wp.dot(xv, xv) - scalar(1.0))
        return xu, xv, G00, G11, half * wp.dot(xu, xv)

    @wp.func
    def energy_density(k: vec4, G00: scalar, G11: scalar, G01: scalar):
        # psi = 1/2 (k0 G00^2 + 2 k1 G00 G11 + k2 G11^2) + k3 G01^2, consistent with the force below
        return scalar(0.5) * (k[0] * G00 * G00 + scalar(2.0) * k[1] * G00 * G11 + k[2] * G11 * G11) + k[3] * G01 * G01

    @wp.func
    def node_force(
        a: int, du: vec3, dv: vec3, xu: vec3, xv: vec3, k: vec4, G00: scalar, G11: scalar, G01: scalar, area: scalar
    ):
        """Force on face node ``a``: -A [k0 G00 fuu + k2 G11 fvv + k1 (G00 fvv + G11 fuu) + k3 G01 fuv]."""
        fuu = du[a] * xu
        fvv = dv[a] * xv
        fuv = du[a] * xv + dv[a] * xu
        return -area * (k[0] * G00 * fuu + k[2] * G11 * fvv + k[1] * (G00 * fvv + G11 * fuu) + k[3] * G01 * fuv)

    @wp.func
    def hessian_block(
        a: int, b: int, du: vec3, dv: vec3, xu: vec3, xv: vec3, k: vec4, G00: scalar, G11: scalar, area: scalar
    ):
        """Block (a, b) of ARCSim's PSD stretching Hessian H = -J (the G01 (Du'Dv + Dv'Du) term dropped)."""
        zero = scalar(0.0)
        g00 = wp.max(G00, zero)
        g11 = wp.max(G11, zero)
        fuv_a = du[a] * xv + dv[a] * xu
        fuv_b = du[b] * xv + dv[b] * xu
        uu = du[a] * du[b]
        vv = dv[a] * dv[b]
        eye = wp.identity(n=3, dtype=scalar)
        h = k[0] * (uu * wp.outer(xu, xu) + (g00 * uu) * eye)
        h += k[2] * (vv * wp.outer(xv, xv) + (g11 * vv) * eye)
        h += k[1] * (
            (du[a] * dv[b]) * wp.outer(xu, xv) + (dv[a] * du[b]) * wp.outer(xv, xu) + (g00 * vv + g11 * uu) * eye
        )
        h += (scalar(0.5) * k[3]) * wp.outer(fuv_a, fuv_b)
        return area * h

    return SimpleNamespace(
        stiffness=stiffness,
        shape_gradients=shape_gradients,
        deformation=deformation,
        energy_density=energy_density,
        node_force=node_force,
        hessian_block=hessian_block,
    )
