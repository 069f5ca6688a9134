"""Shared math of the solver's kernels: float32/float64 matrix conversions, the per-particle
matrices' load and store per array layout, the quadratic B-spline stencil, the polar
decomposition and the constitutive laws (fixed-corotated elasticity, Kelvin-Voigt viscosity)."""

from __future__ import annotations

import warp as wp

from ._module import MODULE


@wp.func(module=MODULE)
def mat33_to_f64(A: wp.mat33) -> wp.mat33d:
    """A float32 3x3 matrix in float64."""
    return wp.mat33d(wp.float64(A[0, 0]), wp.float64(A[0, 1]), wp.float64(A[0, 2]),
                     wp.float64(A[1, 0]), wp.float64(A[1, 1]), wp.float64(A[1, 2]),
                     wp.float64(A[2, 0]), wp.float64(A[2, 1]), wp.float64(A[2, 2]))


@wp.func(module=MODULE)
def mat33_to_f32(A: wp.mat33d) -> wp.mat33:
    """A float64 3x3 matrix rounded to float32."""
    return wp.mat33(float(A[0, 0]), float(A[0, 1]), float(A[0, 2]),
                    float(A[1, 0]), float(A[1, 1]), float(A[1, 2]),
                    float(A[2, 0]), float(A[2, 1]), float(A[2, 2]))


# Per-particle 3x3 matrices (C, F, the P2G terms' affine matrices) come in two layouts
# (_model.matrix_array), and the kernels that read or write them are generic in their array
# type (``Any``): Warp builds one overload per layout, and these functions, overloaded per array
# type, load and store a particle's matrix. On a GPU component by component: a (9, pitch) array
# holds particle p's component k = 3 i + j at [k, p] (pitch: the particle count rounded up to
# 32, so every row starts aligned), and a warp's 32 threads read one component of 32 particles
# from one stretch of memory, where records a particle would touch a sector each. On the CPU as
# records, an (n,) array of matrices: one load a matrix. Both choices are measured in
# benchmarks/results/2026-11-27-layout-and-instructions.md ("the matrices' layout chosen per device").
@wp.func(module=MODULE)
def mat33_at(A: wp.array(dtype=wp.mat33), p: int) -> wp.mat33:
    """Particle ``p``'s matrix of a float32 array of records."""
    return A[p]


@wp.func(module=MODULE)
def mat33_put(A: wp.array(dtype=wp.mat33), p: int, M: wp.mat33):
    """Store particle ``p``'s matrix ``M`` in a float32 array of records."""
    A[p] = M


@wp.func(module=MODULE)
def mat33d_at(A: wp.array(dtype=wp.mat33d), p: int) -> wp.mat33d:
    """Particle ``p``'s matrix of a float64 array of records."""
    return A[p]


@wp.func(module=MODULE)
def mat33d_put(A: wp.array(dtype=wp.mat33d), p: int, M: wp.mat33d):
    """Store particle ``p``'s matrix ``M`` in a float64 array of records."""
    A[p] = M


@wp.func(module=MODULE)
def mat33_at(A: wp.array2d(dtype=float), p: int) -> wp.mat33:  # noqa: F811  (an overload)
    """Particle ``p``'s matrix of a (9, columns) float32 array."""
    return wp.mat33(A[0, p], A[1, p], A[2, p], A[3, p], A[4, p], A[5, p], A[6, p], A[7, p], A[8, p])


@wp.func(module=MODULE)
def mat33_put(A: wp.array2d(dtype=float), p: int, M: wp.mat33):  # noqa: F811  (an overload)
    """Store particle ``p``'s matrix ``M`` in a (9, columns) float32 array."""
    for i in range(3):
        for j in range(3):
            A[3 * i + j, p] = M[i, j]


@wp.func(module=MODULE)
def mat33d_at(A: wp.array2d(dtype=wp.float64), p: int) -> wp.mat33d:  # noqa: F811  (an overload)
    """Particle ``p``'s matrix of a (9, columns) float64 array."""
    return wp.mat33d(A[0, p], A[1, p], A[2, p], A[3, p], A[4, p], A[5, p], A[6, p], A[7, p], A[8, p])


@wp.func(module=MODULE)
def mat33d_put(A: wp.array2d(dtype=wp.float64), p: int, M: wp.mat33d):  # noqa: F811  (an overload)
    """Store particle ``p``'s matrix ``M`` in a (9, columns) float64 array."""
    for i in range(3):
        for j in range(3):
            A[3 * i + j, p] = M[i, j]


# The deformation gradient as its displacement gradient H = F - I in float32 (the model's
# ``deformation_storage = "displacement"``, _model.deformation_array), as positions are kept as
# x0 + u: a (3, 3, columns) float32 array holds H's component (i, j) of particle p at [i, j, p].
# F is read as I + H in float64 and stored back as F - I rounded to float32: a strain's increment
# rounds at H's precision (H's ulp), not at 1's as a float32 F would, and a substep reads and
# writes 36 bytes of it a particle instead of 72.
@wp.func(module=MODULE)
def mat33d_at(A: wp.array3d(dtype=float), p: int) -> wp.mat33d:  # noqa: F811  (an overload)
    """Particle ``p``'s deformation gradient ``I + H`` in float64 from its displacement gradient
    ``H`` in a (3, 3, columns) float32 array."""
    one = wp.float64(1.0)
    return wp.mat33d(one + wp.float64(A[0, 0, p]), wp.float64(A[0, 1, p]), wp.float64(A[0, 2, p]),
                     wp.float64(A[1, 0, p]), one + wp.float64(A[1, 1, p]), wp.float64(A[1, 2, p]),
                     wp.float64(A[2, 0, p]), wp.float64(A[2, 1, p]), one + wp.float64(A[2, 2, p]))


@wp.func(module=MODULE)
def mat33d_put(A: wp.array3d(dtype=float), p: int, M: wp.mat33d):  # noqa: F811  (an overload)
    """Store particle ``p``'s deformation gradient ``M`` as its displacement gradient ``M - I``
    (taken in float64, then rounded to float32) in a (3, 3, columns) float32 array."""
    for i in range(3):
        for j in range(3):
            h = M[i, j]
            if i == j:
                h = h - wp.float64(1.0)
            A[i, j, p] = float(h)


#: the per-particle matrix arrays of each layout (_model.matrix_array): (float32, float64)
MATRIX_ARRAYS = {
    "records": (wp.array(dtype=wp.mat33), wp.array(dtype=wp.mat33d)),
    "components": (wp.array2d(dtype=float), wp.array2d(dtype=wp.float64)),
}
#: the deformation gradients' array as displacement gradients (_model.deformation_array); its
#: kernels take the float32 matrices component by component
DISPLACEMENT_ARRAY = wp.array3d(dtype=float)


def overload_per_layout(kernel: wp.Kernel, *, f32: tuple[str, ...] = (), f64: tuple[str, ...] = ()) -> wp.Kernel:
    """Declare ``kernel``'s overload for each matrix layout: its arguments named in ``f32``
    (float32 matrices) and ``f64`` (float64) take that layout's array type. Declared when the
    module is defined, so every overload is built with it in one go: an overload first made at
    a launch changes the module, and Warp builds the whole module again in the middle of a
    rollout (benchmarks/results/2026-11-27-layout-and-instructions.md)."""
    for a32, a64 in MATRIX_ARRAYS.values():
        wp.overload(kernel, {**dict.fromkeys(f32, a32), **dict.fromkeys(f64, a64)})
    if f64:  # F as displacement gradients, beside float32 matrices component by component
        wp.overload(kernel, {**dict.fromkeys(f32, MATRIX_ARRAYS["components"][0]),
                             **dict.fromkeys(f64, DISPLACEMENT_ARRAY)})
    return kernel


@wp.func(module=MODULE)
def bspline_weights(fx: wp.vec3) -> wp.mat33:
    """Quadratic B-spline weights; row ``k`` holds the weight of stencil node ``k`` per axis.

    ``fx`` is the particle position relative to its base node, in cells (in [0.5, 1.5)).
    """
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.mat33(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])


@wp.func(module=MODULE)
def stencil_base(gx: wp.vec3) -> wp.vec3i:
    """First node of the 3x3x3 stencil of a particle at ``gx`` (position in cells)."""
    return wp.vec3i(int(gx[0] - 0.5), int(gx[1] - 0.5), int(gx[2] - 0.5))


@wp.func(module=MODULE)
def stencil_inside(base: wp.vec3i, lo: wp.vec3i, hi: wp.vec3i) -> bool:
    """Whether the stencil starting at ``base`` lies in the active box [lo, hi). Written so
    that no sum can overflow: a particle flung far away between guard checks has its base
    cast from a huge float, which saturates at the int32 limits (on a GPU), and ``base + 2``
    would wrap round to a small number and let its stencil index outside the grid."""
    for a in range(3):
        if base[a] < lo[a] or base[a] > hi[a] - 3:
            return False
    return True


@wp.func(module=MODULE)
def polar_rotation(A: wp.mat33, q0: wp.quat, max_iter: int, step: float, rational: int) -> wp.quat:
    """Rotation of the polar decomposition of ``A`` (det A > 0), warm-started from ``q0``.

    Mueller et al. 2016, "A Robust Method to Extract the Rotational Part of Deformations":
    rotate ``q`` about the axis that aligns its columns with those of ``A`` until the
    correction angle is below 1e-7 rad (or ``max_iter`` iterations). No SVD. ``max_iter`` must
    not bind (an unconverged rotation puts a spurious stress into every substep).

    ``step`` scales the rotation by the correction once it is below 0.1 rad (larger ones are
    taken whole). Their correction is ``(tr S - S) e / tr S`` for an error ``e`` and the
    stretch ``S``: two thirds of the error near ``S = I``, so a step of 1 (theirs) removes a
    third of the error per iteration, and 1.5 nearly all of it (every error component still
    shrinks for any stretch: the factor stays below 2). Warm-started, 1.5 takes about a third of
    the iterations of 1 to the same rotation
    (benchmarks/results/2026-11-27-layout-and-instructions.md, "Polar iterations").

    ``rational = 1`` takes the corrections below 0.1 rad as the rational quaternion ``(h, 1)``,
    ``h = step omega / 2``, normalized with the product (a rotation by ``2 atan(|h|)``: short of
    the angle asked by ``|h|^2 / 3`` of it, 0.2 % at 0.15 rad), instead of the axis and angle's
    sine and cosine, and divides by the denominator once: the same fixed point (the rotation
    at which the correction vanishes) in fewer instructions an iteration.
    """
    q = q0
    a0 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    a1 = wp.vec3(A[0, 1], A[1, 1], A[2, 1])
    a2 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
    for _ in range(max_iter):
        R = wp.quat_to_matrix(q)
        r0 = wp.vec3(R[0, 0], R[1, 0], R[2, 0])
        r1 = wp.vec3(R[0, 1], R[1, 1], R[2, 1])
        r2 = wp.vec3(R[0, 2], R[1, 2], R[2, 2])
        num = wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)
        den = wp.abs(wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)) + 1.0e-9
        if rational == 1:
            small = num * (1.0 / den)
            angle2 = wp.dot(small, small)
            if angle2 < 1.0e-14:
                break
            if angle2 < 0.01:
                h = (0.5 * step) * small
                q = wp.normalize(wp.quat(h[0], h[1], h[2], 1.0) * q)
                continue
        omega = num / den
        angle = wp.length(omega)
        if angle < 1.0e-7:
            break
        scale = float(1.0)
        if angle < 0.1:
            scale = step
        q = wp.normalize(wp.quat_from_axis_angle(omega / angle, scale * angle) * q)
    return q


@wp.func(module=MODULE)
def fixed_corotated_kirchhoff(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Kirchhoff stress tau = P F^T = 2 mu (F - R) F^T + lam (J - 1) J I [Pa]."""
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func(module=MODULE)
def kelvin_voigt_kirchhoff(L: wp.mat33, J: float, mu: float, lam: float, retardation: float) -> wp.mat33:
    """Kirchhoff viscous stress of a Kelvin-Voigt solid whose viscosity is proportional to
    its stiffness: tau_v = J beta (2 mu D + lam tr(D) I) [Pa], D = sym(L) the rate of
    deformation [1/s] from the velocity gradient ``L`` (the transfer's affine matrix), beta =
    ``retardation`` [s] (stiffness-proportional Rayleigh damping: the modal damping ratio
    is beta omega / 2)."""
    D = 0.5 * (L + wp.transpose(L))
    tr = D[0, 0] + D[1, 1] + D[2, 2]
    return (J * retardation) * (2.0 * mu * D + wp.identity(n=3, dtype=float) * (lam * tr))



@wp.func(module=MODULE)
def vec4_head(a: wp.vec4) -> wp.vec3:
    """The first three components of ``a``."""
    return wp.vec3(a[0], a[1], a[2])


@wp.func(module=MODULE)
def mat33_from_rows(r0: wp.vec4, r1: wp.vec4, r2: wp.vec4) -> wp.mat33:
    """The matrix whose rows are the first three components of ``r0``, ``r1``, ``r2``."""
    return wp.mat33(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2])

