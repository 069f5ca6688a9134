"""Warp kernels of the MLS-MPM solver (quadratic B-splines, fixed-corotated elasticity) with an
APIC or an affine-FLIP particle-grid transfer.

One thread per particle or per grid node; inputs before outputs. The same kernels run on
the CPU and on CUDA. Grid kernels run over the *active box* only (the grid region that the
particles' stencils can reach), given as an offset ``lo`` and the launch dimensions.

Conventions: ``n_grid`` nodes per axis at positions ``i * dx``; a particle at ``x`` scatters
to the 3x3x3 nodes starting at ``base = int(x / dx - 0.5)``.

Transfers (``affine_flip`` flag of :func:`p2g`, :func:`grid_zero`, :func:`grid_update`,
:func:`g2p`): APIC (Jiang et al. 2015) replaces a particle's velocity ``v`` and affine
matrix ``C`` by the grid's, so the part of the particle velocity field that the grid cannot
hold is lost at every transfer, a numerical damping per substep. Affine FLIP (the AFLIP
family of Fei et al. 2021) adds the grid's *increment* instead: P2G also scatters the
momentum without this substep's stress (``grid_mv_old``), and G2P takes
``v <- a (v + sum w du) + (1 - a) v_pic`` and
``C <- a (C + sum w (4/dx^2) du (x_i - x_p)^T) + (1 - a) C_pic`` with the node increment
``du = u_new - u_old`` and ``a = exp(-dt / tau)`` (``tau`` a relaxation time towards PIC, so
the remaining dissipation is per second, not per substep). Positions advect with the grid
(PIC) velocity and ``F`` updates with the grid gradient ``C_pic`` in both transfers.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .. import _warp  # noqa: F401  (Warp's log level: no start-up banner in logs and CLI output)

wp.set_module_options({"enable_backward": False})

#: cap on the registers per thread of the GPU's heavy particle kernels (G2P and the fused G2P;
#: CUDA ``__maxnreg__``, ignored on the CPU): more threads resident per SM to hide their memory
#: latency, at the cost of a few spills. The caps tried and their substep times are in
#: benchmarks/results/2026-11-27-layout-and-instructions.md
CUDA_MAX_REGISTERS = 80


# --------------------------------------------------------------------------------------
# shared math
# --------------------------------------------------------------------------------------
@wp.func
def mat33_to_f64(A: wp.mat33) -> wp.mat33d:
    """A float32 3x3 matrix in float64."""
    return wp.mat33d(wp.float64(A[0, 0]), wp.float64(A[0, 1]), wp.float64(A[0, 2]),
                     wp.float64(A[1, 0]), wp.float64(A[1, 1]), wp.float64(A[1, 2]),
                     wp.float64(A[2, 0]), wp.float64(A[2, 1]), wp.float64(A[2, 2]))


@wp.func
def mat33_to_f32(A: wp.mat33d) -> wp.mat33:
    """A float64 3x3 matrix rounded to float32."""
    return wp.mat33(float(A[0, 0]), float(A[0, 1]), float(A[0, 2]),
                    float(A[1, 0]), float(A[1, 1]), float(A[1, 2]),
                    float(A[2, 0]), float(A[2, 1]), float(A[2, 2]))


# Per-particle 3x3 matrices (C, F, the P2G terms' affine matrices) come in two layouts
# (_solver.matrix_array), and the kernels that read or write them are generic in their array
# type (``Any``): Warp builds one overload per layout, and these functions, overloaded per array
# type, load and store a particle's matrix. On a GPU component by component: a (9, pitch) array
# holds particle p's component k = 3 i + j at [k, p] (pitch: the particle count rounded up to
# 32, so every row starts aligned), and a warp's 32 threads read one component of 32 particles
# from one stretch of memory (as one 36- or 72-byte record a particle, each component's read
# touched 32 sectors and a block's records outgrew the L1 cache: benchmarks/results/2026-11-27-layout-and-instructions.md,
# "the matrices' layout chosen per device"). On the CPU as records, an (n,) array of matrices: one load a matrix
# (component by component, or as strided records, measured 3-12 % slower there).
@wp.func
def mat33_at(A: wp.array(dtype=wp.mat33), p: int) -> wp.mat33:
    """Particle ``p``'s matrix of a float32 array of records."""
    return A[p]


@wp.func
def mat33_put(A: wp.array(dtype=wp.mat33), p: int, M: wp.mat33):
    """Store particle ``p``'s matrix ``M`` in a float32 array of records."""
    A[p] = M


@wp.func
def mat33d_at(A: wp.array(dtype=wp.mat33d), p: int) -> wp.mat33d:
    """Particle ``p``'s matrix of a float64 array of records."""
    return A[p]


@wp.func
def mat33d_put(A: wp.array(dtype=wp.mat33d), p: int, M: wp.mat33d):
    """Store particle ``p``'s matrix ``M`` in a float64 array of records."""
    A[p] = M


@wp.func
def mat33_at(A: wp.array2d(dtype=float), p: int) -> wp.mat33:  # noqa: F811  (an overload)
    """Particle ``p``'s matrix of a (9, columns) float32 array."""
    return wp.mat33(A[0, p], A[1, p], A[2, p], A[3, p], A[4, p], A[5, p], A[6, p], A[7, p], A[8, p])


@wp.func
def mat33_put(A: wp.array2d(dtype=float), p: int, M: wp.mat33):  # noqa: F811  (an overload)
    """Store particle ``p``'s matrix ``M`` in a (9, columns) float32 array."""
    for i in range(3):
        for j in range(3):
            A[3 * i + j, p] = M[i, j]


@wp.func
def mat33d_at(A: wp.array2d(dtype=wp.float64), p: int) -> wp.mat33d:  # noqa: F811  (an overload)
    """Particle ``p``'s matrix of a (9, columns) float64 array."""
    return wp.mat33d(A[0, p], A[1, p], A[2, p], A[3, p], A[4, p], A[5, p], A[6, p], A[7, p], A[8, p])


@wp.func
def mat33d_put(A: wp.array2d(dtype=wp.float64), p: int, M: wp.mat33d):  # noqa: F811  (an overload)
    """Store particle ``p``'s matrix ``M`` in a (9, columns) float64 array."""
    for i in range(3):
        for j in range(3):
            A[3 * i + j, p] = M[i, j]


# The deformation gradient as its displacement gradient H = F - I in float32 (the model's
# ``deformation_storage = "displacement"``, _solver.deformation_array), as positions are kept as
# x0 + u: a (3, 3, columns) float32 array holds H's component (i, j) of particle p at [i, j, p].
# F is read as I + H in float64 and stored back as F - I rounded to float32: a strain's increment
# rounds at H's precision (H's ulp), not at 1's as a float32 F would, and a substep reads and
# writes 36 bytes of it a particle instead of 72.
@wp.func
def mat33d_at(A: wp.array3d(dtype=float), p: int) -> wp.mat33d:  # noqa: F811  (an overload)
    """Particle ``p``'s deformation gradient ``I + H`` in float64 from its displacement gradient
    ``H`` in a (3, 3, columns) float32 array."""
    one = wp.float64(1.0)
    return wp.mat33d(one + wp.float64(A[0, 0, p]), wp.float64(A[0, 1, p]), wp.float64(A[0, 2, p]),
                     wp.float64(A[1, 0, p]), one + wp.float64(A[1, 1, p]), wp.float64(A[1, 2, p]),
                     wp.float64(A[2, 0, p]), wp.float64(A[2, 1, p]), one + wp.float64(A[2, 2, p]))


@wp.func
def mat33d_put(A: wp.array3d(dtype=float), p: int, M: wp.mat33d):  # noqa: F811  (an overload)
    """Store particle ``p``'s deformation gradient ``M`` as its displacement gradient ``M - I``
    (taken in float64, then rounded to float32) in a (3, 3, columns) float32 array."""
    for i in range(3):
        for j in range(3):
            h = M[i, j]
            if i == j:
                h = h - wp.float64(1.0)
            A[i, j, p] = float(h)


#: the per-particle matrix arrays of each layout (_solver.matrix_array): (float32, float64)
MATRIX_ARRAYS = {
    "records": (wp.array(dtype=wp.mat33), wp.array(dtype=wp.mat33d)),
    "components": (wp.array2d(dtype=float), wp.array2d(dtype=wp.float64)),
}
#: the deformation gradients' array as displacement gradients (_solver.deformation_array); its
#: kernels take the float32 matrices component by component
DISPLACEMENT_ARRAY = wp.array3d(dtype=float)


def overload_per_layout(kernel: wp.Kernel, *, f32: tuple[str, ...] = (), f64: tuple[str, ...] = ()) -> wp.Kernel:
    """Declare ``kernel``'s overload for each matrix layout: its arguments named in ``f32``
    (float32 matrices) and ``f64`` (float64) take that layout's array type. Declared when the
    module is defined, so every overload is built with it in one go: an overload first made at
    a launch changes the module, and Warp builds the whole module again (on a fresh GPU machine
    a paper-scale rollout exporting F took 20.3 s instead of ~4, its first gather of F
    rebuilding the module)."""
    for a32, a64 in MATRIX_ARRAYS.values():
        wp.overload(kernel, {**dict.fromkeys(f32, a32), **dict.fromkeys(f64, a64)})
    if f64:  # F as displacement gradients, beside float32 matrices component by component
        wp.overload(kernel, {**dict.fromkeys(f32, MATRIX_ARRAYS["components"][0]),
                             **dict.fromkeys(f64, DISPLACEMENT_ARRAY)})
    return kernel


@wp.func
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


@wp.func
def stencil_base(gx: wp.vec3) -> wp.vec3i:
    """First node of the 3x3x3 stencil of a particle at ``gx`` (position in cells)."""
    return wp.vec3i(int(gx[0] - 0.5), int(gx[1] - 0.5), int(gx[2] - 0.5))


@wp.func
def stencil_inside(base: wp.vec3i, lo: wp.vec3i, hi: wp.vec3i) -> bool:
    """Whether the stencil starting at ``base`` lies in the active box [lo, hi)."""
    for a in range(3):
        if base[a] < lo[a] or base[a] + 2 >= hi[a]:
            return False
    return True


@wp.func
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
    shrinks for any stretch: the factor stays below 2). Warm-started on the default Pillow,
    8.1 iterations a particle on average with 1, 2.8 with 1.5, to the same rotation
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


@wp.func
def fixed_corotated_kirchhoff(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Kirchhoff stress tau = P F^T = 2 mu (F - R) F^T + lam (J - 1) J I [Pa]."""
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func
def kelvin_voigt_kirchhoff(L: wp.mat33, J: float, mu: float, lam: float, retardation: float) -> wp.mat33:
    """Kirchhoff viscous stress of a Kelvin-Voigt solid whose viscosity is proportional to
    its stiffness: tau_v = J beta (2 mu D + lam tr(D) I) [Pa], D = sym(L) the rate of
    deformation [1/s] from the velocity gradient ``L`` (the transfer's affine matrix), beta =
    ``retardation`` [s] (stiffness-proportional Rayleigh damping: the modal damping ratio
    is beta omega / 2)."""
    D = 0.5 * (L + wp.transpose(L))
    tr = D[0, 0] + D[1, 1] + D[2, 2]
    return (J * retardation) * (2.0 * mu * D + wp.identity(n=3, dtype=float) * (lam * tr))


# --------------------------------------------------------------------------------------
# grid kernels (launched over the active box)
# --------------------------------------------------------------------------------------
@wp.kernel
def state_rest(F: Any, rot: wp.array(dtype=wp.quat)):
    """A particle at rest in its reference shape: ``F = I`` and its rotation the identity
    (the initial state, set on the device: no host array, no copy)."""
    p = wp.tid()
    mat33d_put(F, p, wp.identity(n=3, dtype=wp.float64))
    rot[p] = wp.quat_identity()


@wp.kernel
def grid_zero(
    lo: wp.vec3i,
    affine_flip: int,
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
):
    """Zero the grid momentum and mass (and the stress-free momentum when ``affine_flip = 1``)."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    grid_mv[gi, gj, gk] = wp.vec3(0.0)
    grid_m[gi, gj, gk] = 0.0
    if affine_flip == 1:
        grid_mv_old[gi, gj, gk] = wp.vec3(0.0)


@wp.func
def wall_velocity(g: wp.vec3i, v: wp.vec3, n_grid: int, padding: int, sticky: int) -> wp.vec3:
    """Domain walls: a node within ``padding`` of a face loses its outward normal velocity
    (``sticky=0``, slip) or all velocity (``sticky=1``)."""
    for a in range(3):
        if g[a] < padding and v[a] < 0.0:
            if sticky == 1:
                v = wp.vec3(0.0)
            else:
                v[a] = 0.0
        if g[a] >= n_grid - padding and v[a] > 0.0:
            if sticky == 1:
                v = wp.vec3(0.0)
            else:
                v[a] = 0.0
    return v


@wp.func
def updated_node(g: wp.vec3i, m: float, mv: wp.vec3, mv_old: wp.vec3, dt: float, gravity: wp.vec3, damping: float,
                 walls: int, n_grid: int, padding: int, sticky: int, affine_flip: int):
    """A node's velocity and (``affine_flip = 1``) old velocity ``u_old`` [m/s] from its mass
    ``m`` [kg], momentum ``mv`` and stress-free momentum ``mv_old`` [kg m/s]: gravity,
    velocity damping (scale per substep) and, with ``walls = 1``, the domain walls
    (:func:`wall_velocity`)."""
    v = wp.vec3(0.0)
    if m > 1.0e-15:
        v = (mv / m + dt * gravity) * damping
    v_old = wp.vec3(0.0)
    if affine_flip == 1:
        if m > 1.0e-15:
            v_old = mv_old / m
    if walls == 1:
        v = wall_velocity(g, v, n_grid, padding, sticky)
    return v, v_old


@wp.kernel
def grid_update(
    lo: wp.vec3i,
    dt: float,
    gravity: wp.vec3,
    damping: float,
    walls: int,
    n_grid: int,
    padding: int,
    sticky: int,
    affine_flip: int,
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
):
    """Momentum -> velocity, gravity, velocity damping (scale per substep); in place. With
    ``walls = 1`` the domain walls follow in the same pass (as :func:`grid_bc_walls` would:
    one pass over the box instead of two). With ``affine_flip = 1`` the stress-free momentum
    ``grid_mv_old`` becomes the old node velocity ``u_old`` [m/s] in the same pass."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    mv_old = wp.vec3(0.0)
    if affine_flip == 1:
        mv_old = grid_mv_old[gi, gj, gk]
    v, v_old = updated_node(wp.vec3i(gi, gj, gk), grid_m[gi, gj, gk], grid_mv[gi, gj, gk], mv_old, dt, gravity, damping,
                            walls, n_grid, padding, sticky, affine_flip)
    if affine_flip == 1:
        grid_mv_old[gi, gj, gk] = v_old
    grid_mv[gi, gj, gk] = v


# Fixed-point P2G sums (``MPMSolver(deterministic=True)``, the bitwise-reproducible P2G). Float
# atomics add a node's contributions in the order the GPU schedules them, so their rounding, and
# a GPU rollout's last bits, vary from run to run. Integer additions give the same sum in any
# order. So the windows' run sums (each summed in a fixed order) go into int64 node sums
# ``q`` [7, n_grid^3] (rows: momentum x, y, z, mass, stress-free momentum x, y, z), in units
# of ``1 / scale`` [kg or kg m/s], where ``scale`` is a power of two: a float32 times it is
# exact, so a run sum converts without rounding where it is above 2^24 units. The update reads
# them back as floats and zeroes them for the next substep (:func:`grid_update_fixed`).
#: the largest magnitude one addition to a fixed-point sum may have (units); the scales put the
#: object's whole mass, and its mass times 64 dx / dt, at 2^61, so a node's sum stays below 2^63
FIXED_LIMIT = float(2.0**61)


@wp.func
def fixed_add(q: wp.array2d(dtype=wp.int64), row: int, node: int, x: float, scale: float,
              overflow: wp.array(dtype=wp.int32)):
    """Add ``x`` to the fixed-point sum ``q[row, node]`` in units of ``1 / scale``, rounded to
    the nearest unit; a value at or above :data:`FIXED_LIMIT` units (or not finite) is not
    added, and ``overflow[0]`` is set."""
    y = x * scale
    if wp.abs(y) < FIXED_LIMIT:
        wp.atomic_add(q, row, node, wp.int64(wp.round(y)))
    else:
        overflow[0] = 1


@wp.func
def fixed_value(q: wp.array2d(dtype=wp.int64), row: int, node: int, unit: wp.float64) -> float:
    """The fixed-point sum ``q[row, node]`` as a float (``unit`` = 1 / scale)."""
    return float(wp.float64(q[row, node]) * unit)


@wp.kernel
def grid_update_fixed(
    lo: wp.vec3i,
    dt: float,
    gravity: wp.vec3,
    damping: float,
    walls: int,
    n_grid: int,
    padding: int,
    sticky: int,
    affine_flip: int,
    unit_m: wp.float64,
    unit_p: wp.float64,
    q: wp.array2d(dtype=wp.int64),
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
):
    """:func:`grid_update` from the fixed-point sums ``q`` (mass in units of ``unit_m`` [kg],
    momenta of ``unit_p`` [kg m/s]): writes the mass, velocity and (``affine_flip = 1``) old
    velocity of every node of the box, and zeroes its sums for the next substep, so the box
    needs no zeroing pass."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    node = (gi * n_grid + gj) * n_grid + gk
    m = fixed_value(q, 3, node, unit_m)
    mv = wp.vec3(fixed_value(q, 0, node, unit_p), fixed_value(q, 1, node, unit_p), fixed_value(q, 2, node, unit_p))
    mv_old = wp.vec3(0.0)
    if affine_flip == 1:
        mv_old = wp.vec3(fixed_value(q, 4, node, unit_p), fixed_value(q, 5, node, unit_p), fixed_value(q, 6, node, unit_p))
    for r in range(7):
        q[r, node] = wp.int64(0)
    v, v_old = updated_node(wp.vec3i(gi, gj, gk), m, mv, mv_old, dt, gravity, damping, walls, n_grid, padding, sticky,
                            affine_flip)
    grid_m[gi, gj, gk] = m
    if affine_flip == 1:
        grid_mv_old[gi, gj, gk] = v_old
    grid_mv[gi, gj, gk] = v


# P2G sums as vec4 records (``MPMSolver(window_atomics="vector")``). The window sums add a run's
# sums to a node with one float atomic a component: four a node under APIC (momentum and mass),
# seven under affine FLIP. Devices of compute capability 9.0 and later add a 16-byte vector
# to global memory with one atomic, so here the sums go into node records, momentum and mass
# (``sums_mvm``) and the stress-free momentum (``sums_old``, its fourth component unused), each
# added with one :func:`vec4_atomic_add`; the update reads them back and zeroes them for the next
# substep (:func:`grid_update_records`), as it does the fixed-point sums. Older devices add the
# components one by one; the CPU adds them in order, the bits of the float arrays' atomics.
@wp.func_native("""#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
atomicAdd(reinterpret_cast<float4*>(a.data) + i, make_float4(x.c[0], x.c[1], x.c[2], x.c[3]));
#elif defined(__CUDA_ARCH__)
float* r = reinterpret_cast<float*>(a.data) + 4 * i;
atomicAdd(r, x.c[0]); atomicAdd(r + 1, x.c[1]); atomicAdd(r + 2, x.c[2]); atomicAdd(r + 3, x.c[3]);
#else
float* r = reinterpret_cast<float*>(a.data) + 4 * i;
r[0] += x.c[0]; r[1] += x.c[1]; r[2] += x.c[2]; r[3] += x.c[3];
#endif
""")
def vec4_atomic_add(a: wp.array(dtype=wp.vec4), i: int, x: wp.vec4):
    """Add ``x`` to record ``i`` of the flat array ``a``: one vector atomic on a device of
    compute capability 9.0 or later, four float atomics on an older one, four additions in
    component order on the CPU."""
    ...


@wp.kernel
def grid_update_records(
    lo: wp.vec3i,
    dt: float,
    gravity: wp.vec3,
    damping: float,
    walls: int,
    n_grid: int,
    padding: int,
    sticky: int,
    affine_flip: int,
    sums_mvm: wp.array(dtype=wp.vec4),
    sums_old: wp.array(dtype=wp.vec4),
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
):
    """:func:`grid_update` from the node records ``sums_mvm`` (momentum [kg m/s], mass [kg])
    and ``sums_old`` (stress-free momentum, with ``affine_flip = 1``), flat over the
    ``n_grid``^3 nodes: writes the mass, velocity and (``affine_flip = 1``) old velocity of
    every node of the box and zeroes its records for the next substep, so the box needs no
    zeroing pass."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    node = (gi * n_grid + gj) * n_grid + gk
    r = sums_mvm[node]
    sums_mvm[node] = wp.vec4(0.0)
    mv_old = wp.vec3(0.0)
    if affine_flip == 1:
        mv_old = vec4_head(sums_old[node])
        sums_old[node] = wp.vec4(0.0)
    v, v_old = updated_node(wp.vec3i(gi, gj, gk), r[3], vec4_head(r), mv_old, dt, gravity, damping, walls, n_grid,
                            padding, sticky, affine_flip)
    grid_m[gi, gj, gk] = r[3]
    if affine_flip == 1:
        grid_mv_old[gi, gj, gk] = v_old
    grid_mv[gi, gj, gk] = v


@wp.kernel
def grid_bc_walls(
    lo: wp.vec3i,
    n_grid: int,
    padding: int,
    sticky: int,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Domain walls on node velocities (see :func:`wall_velocity`)."""
    i, j, k = wp.tid()
    g = wp.vec3i(i + lo[0], j + lo[1], k + lo[2])
    grid_v[g[0], g[1], g[2]] = wall_velocity(g, grid_v[g[0], g[1], g[2]], n_grid, padding, sticky)


@wp.func
def inside_box(p: wp.vec3, half_size: wp.vec3) -> bool:
    """Whether ``p`` (relative to a box's centre) lies in the closed box."""
    return wp.abs(p[0]) <= half_size[0] and wp.abs(p[1]) <= half_size[1] and wp.abs(p[2]) <= half_size[2]


@wp.func
def nearest_face_normal(p: wp.vec3, half_size: wp.vec3) -> wp.vec3:
    """Outward unit normal of the box face nearest to ``p`` (inside, relative to the centre)."""
    axis = int(0)
    depth = half_size[0] - wp.abs(p[0])
    for a in range(1, 3):
        d = half_size[a] - wp.abs(p[a])
        if d < depth:
            depth = d
            axis = a
    n = wp.vec3(0.0)
    if p[axis] >= 0.0:
        n[axis] = 1.0
    else:
        n[axis] = -1.0
    return n


@wp.kernel
def grid_bc_cuboid(
    lo: wp.vec3i,
    dx: float,
    center: wp.vec3,
    half_size: wp.vec3,
    velocity: wp.vec3,
    friction: float,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """A held support: nodes inside the box take the prescribed velocity (``friction < 0``,
    sticky), or meet a Coulomb contact with coefficient ``friction >= 0``.

    Coulomb contact: with the relative velocity ``u = v - velocity`` and the outward normal
    ``n`` of the box face nearest to the node, an approaching node (``u.n < 0``) loses its
    normal component and its tangential speed drops by ``friction * |u.n|`` (to zero at
    most: static friction); a separating node (``u.n >= 0``) is left free.
    """
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    p = wp.vec3(float(gi), float(gj), float(gk)) * dx - center
    if inside_box(p, half_size):
        if friction < 0.0:
            grid_v[gi, gj, gk] = velocity
        else:
            n = nearest_face_normal(p, half_size)
            u = grid_v[gi, gj, gk] - velocity
            un = wp.dot(u, n)
            if un < 0.0:
                ut = u - un * n
                speed = wp.length(ut)
                slowed = speed + friction * un
                if slowed > 0.0:
                    ut = ut * (slowed / speed)
                else:
                    ut = wp.vec3(0.0)
                grid_v[gi, gj, gk] = velocity + ut


# --------------------------------------------------------------------------------------
# particle kernels
# --------------------------------------------------------------------------------------
@wp.func
def p2g_terms(vp: wp.vec3, Cp: wp.mat33, Fd: wp.mat33d, q0: wp.quat, m: float, volp: float, mup: float, lamp: float,
              inv_dx: float, dt: float, polar_iters: int, polar_step: float, polar_rational: int, retardation: float):
    """A particle's stress and transfer terms from its velocity ``vp`` [m/s], affine matrix
    ``Cp`` [1/s], deformation gradient ``Fd`` (float64) and last rotation ``q0``: the
    warm-started rotation, the affine matrix of the transfer (stress and APIC terms) and its
    APIC term alone (fixed-corotated stress, plus the Kelvin-Voigt viscous stress when
    ``retardation`` [s] > 0)."""
    Fp = mat33_to_f32(Fd)
    q = polar_rotation(Fp, q0, polar_iters, polar_step, polar_rational)
    tau = fixed_corotated_kirchhoff(Fp, wp.quat_to_matrix(q), mup, lamp)
    if retardation > 0.0:
        tau = tau + kelvin_voigt_kirchhoff(Cp, wp.determinant(Fp), mup, lamp, retardation)
    mC = m * Cp
    affine = (-dt * volp * 4.0 * inv_dx * inv_dx) * tau + mC
    return q, affine, mC


@wp.func
def p2g_particle(
    p: int,
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_mask: wp.array(dtype=wp.int32),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
):
    """Particle ``p``'s part of P2G: the probe impulse (``v += f / m dt``, written back), the
    warm-started rotation (written back) and :func:`p2g_terms`; returns the velocity,
    the affine matrix of the transfer (stress and APIC terms) and its APIC term alone."""
    m = mass[p]
    vp = v[p]
    if probe_on == 1 and probe_mask[p] != 0:
        vp = vp + probe_force * (dt / m)
        v[p] = vp
    q, affine, mC = p2g_terms(vp, mat33_at(C, p), mat33d_at(F, p), rot[p], m, vol[p], mu[p], lam[p], inv_dx, dt,
                              polar_iters, polar_step, polar_rational, retardation)
    rot[p] = q
    return vp, affine, mC


@wp.kernel
def p2g(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_mask: wp.array(dtype=wp.int32),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    lo: wp.vec3i,
    hi: wp.vec3i,
    affine_flip: int,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
    grid_mv_old: wp.array3d(dtype=wp.vec3),
    overrun: wp.array(dtype=wp.int32),
):
    """Probe impulse (``v += f / m dt``), fixed-corotated stress, affine scatter to the grid;
    with ``affine_flip = 1`` also the momentum without the stress term into ``grid_mv_old``
    (the probe impulse is in both: it is the particle's velocity, not a grid force)."""
    p = wp.tid()
    m = mass[p]
    vp, affine, mC = p2g_particle(p, C, F, mass, vol, mu, lam, probe_mask, probe_force, probe_on, inv_dx, dt, polar_iters,
                                  polar_step, polar_rational, retardation, v, rot)
    dx = 1.0 / inv_dx

    gx = (x0[p] + u[p]) * inv_dx
    base = stencil_base(gx)
    if not stencil_inside(base, lo, hi):
        wp.atomic_add(overrun, 0, 1)
        return
    fx = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    w = bspline_weights(fx)
    mv = m * vp
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gi = base[0] + i
                gj = base[1] + j
                gk = base[2] + k
                wp.atomic_add(grid_mv, gi, gj, gk, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, gi, gj, gk, weight * m)
                if affine_flip == 1:
                    wp.atomic_add(grid_mv_old, gi, gj, gk, weight * (mv + mC * dpos))


# -- P2G by cells (the GPU path) ---------------------------------------------------------
# The scatter P2G above adds 27 contributions per particle to the grid with float atomics;
# where many particles share a cell (the paper-scale assets' shells: up to ~200 per cell) the
# GPU serializes those atomics on the shared nodes. By cells: each particle's contribution
# terms and the key of its stencil base cell are computed once, in the particles' own order
# (``p2g_prepare``); the particles are sorted by key (``p2g_sort_keys`` and a radix sort, every
# few substeps: between sorts a particle that changed cells only cuts its run short), and the
# sorted particles are summed by windows (:func:`p2g_windows`): one atomic per run of particles
# of one base cell and stencil node instead of one per particle. The same sums, in another
# order (float rounding differs from the scatter's).


@wp.func
def p2g_store(p: int, gx: wp.vec3, aff: wp.mat33, lo: wp.vec3i, hi: wp.vec3i, n_grid: int, none_key: int,
              fx: wp.array(dtype=wp.vec3), affine: Any, keys: wp.array(dtype=wp.int32),
              overrun: wp.array(dtype=wp.int32)):
    """Store particle ``p``'s P2G terms at grid position ``gx`` [cells] (see :func:`p2g_prepare`)."""
    base = stencil_base(gx)
    if stencil_inside(base, lo, hi):
        keys[p] = (base[0] * n_grid + base[1]) * n_grid + base[2]
        fx[p] = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        mat33_put(affine, p, aff)
    else:
        wp.atomic_add(overrun, 0, 1)
        keys[p] = none_key


@wp.kernel
def p2g_prepare(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    probe_mask: wp.array(dtype=wp.int32),
    probe_force: wp.vec3,
    probe_on: int,
    inv_dx: float,
    dt: float,
    polar_iters: int,
    polar_step: float,
    polar_rational: int,
    retardation: float,
    lo: wp.vec3i,
    hi: wp.vec3i,
    n_grid: int,
    none_key: int,
    v: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.quat),
    fx: wp.array(dtype=wp.vec3),
    affine: Any,
    keys: wp.array(dtype=wp.int32),
    overrun: wp.array(dtype=wp.int32),
):
    """The per-particle half of :func:`p2g` (:func:`p2g_particle`), in the particles' order:
    the position in the base cell ``fx`` [cells], the affine matrix of stress and APIC terms
    ``affine`` and the sort key ``keys``: the base cell's index, or ``none_key`` (above every
    cell's) outside the active box; the probe's impulse goes into ``v``. The momentum and mass
    and affine FLIP's APIC term alone, ``m C``, are not stored: the sums form them from the
    state's ``v`` and ``C`` and the model's mass (:func:`momentum_mass`, :func:`apic_term`),
    which stay as they are until G2P: the same products."""
    p = wp.tid()
    vp, aff, mCp = p2g_particle(p, C, F, mass, vol, mu, lam, probe_mask, probe_force, probe_on, inv_dx, dt, polar_iters,
                                polar_step, polar_rational, retardation, v, rot)
    p2g_store(p, (x0[p] + u[p]) * inv_dx, aff, lo, hi, n_grid, none_key, fx, affine, keys, overrun)


@wp.kernel
def p2g_sort_keys(keys: wp.array(dtype=wp.int32), sort_keys: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32)):
    """The radix sort's input: a copy of the keys and the identity order."""
    p = wp.tid()
    sort_keys[p] = keys[p]
    order[p] = p


@wp.func
def stencil_offset(n: int) -> wp.vec3i:
    """Stencil node ``n`` (0..26) of a base cell as its offset ``(i, j, k)``, ``n = 9 i + 3 j + k``."""
    return wp.vec3i(n // 9, (n // 3) % 3, n % 3)


@wp.func
def momentum_mass(v: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), p: int) -> wp.vec4:
    """Particle ``p``'s momentum [kg m/s] ([xyz]) and mass [kg] ([w]) for P2G, from the state's
    velocity (which holds this substep's probe impulse once the per-particle P2G half has run)
    and the model's mass: the product :func:`p2g_particle` forms, bit for bit, formed where it
    is summed instead of stored (a 16-byte write a particle and substep saved)."""
    m = mass[p]
    mvp = m * v[p]
    return wp.vec4(mvp[0], mvp[1], mvp[2], m)


@wp.func
def apic_term(q: wp.vec4, C: Any, p: int) -> wp.mat33:
    """Particle ``p``'s APIC term ``m C`` [kg/s] of the affine-FLIP transfer, from its momentum
    and mass ``q`` (:func:`momentum_mass`; mass in ``q[3]``) and the state's affine velocity
    ``C``: the product :func:`p2g_terms` forms, bit for bit, formed where it is summed instead
    of stored (a 36-byte write a particle and substep saved)."""
    return q[3] * mat33_at(C, p)


@wp.func
def node_term(weight: float, f: wp.vec3, q: wp.vec4, A: wp.mat33, M: wp.mat33, i: int, j: int, k: int, dx: float,
              affine_flip: int):
    """One particle's contribution to the stencil node ``(i, j, k)`` of its base cell, from its
    weight at the node ``weight`` (the product of its B-spline weights along x, y and z, in that
    order) and its P2G terms (position in the cell ``f`` [cells], momentum and mass ``q``, affine
    matrices ``A`` and ``M``): momentum [kg m/s], mass [kg], and the stress-free momentum (affine
    FLIP only, else 0)."""
    dpos = (wp.vec3(float(i), float(j), float(k)) - f) * dx
    mvp = wp.vec3(q[0], q[1], q[2])
    old = wp.vec3(0.0)
    if affine_flip == 1:
        old = weight * (mvp + M * dpos)
    return weight * (mvp + A * dpos), weight * q[3], old


# P2G by windows (W = ``MPMSolver.cell_chunk``): one block of ``W`` threads takes the ``W``
# sorted positions ``b W .. b W + W - 1``; its threads put those particles' terms in shared
# memory together, then each thread sums one run of equal keys (a window is cut where the key
# changes and at its ends) to one stencil node from shared memory, in slot order, and adds the
# sum with one atomic (:func:`window_sums`). Staging the terms once a window spares each of a
# run's threads a chain of dependent global loads through the sort's order (the measurements,
# windows of other sizes among them, are in
# benchmarks/results/2026-11-27-window-sums-and-reference.md).
@wp.func
def window_run_sum(t_key: Any, t_end: Any, t_runs: Any, q: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any, t_mC: Any,
                   n_grid: int, dx: float, affine_flip: int):
    """The (run, stencil node) pair ``q`` (run ``q // 27``, node ``q % 27``) of a window's staged
    terms (see :func:`window_sums`): the run's :func:`node_term` summed to the node in slot
    order, and the node's index in the grid."""
    r = q // 27
    s = t_runs[r]
    e = t_end[s]
    key = t_key[s]
    n = q - 27 * r
    o = stencil_offset(n)
    sum_mv = wp.vec3(0.0)
    sum_m = float(0.0)
    sum_old = wp.vec3(0.0)
    for t in range(s, e):
        weight = t_w[t, o[0]] * t_w[t, 3 + o[1]] * t_w[t, 6 + o[2]]
        M = wp.mat33(0.0)
        if affine_flip == 1:
            M = mat33_from_rows(t_mC[t, 0], t_mC[t, 1], t_mC[t, 2])
        d_mv, d_m, d_old = node_term(weight, vec4_head(t_fx[t]), t_mv[t],
                                     mat33_from_rows(t_aff[t, 0], t_aff[t, 1], t_aff[t, 2]), M, o[0], o[1], o[2], dx,
                                     affine_flip)
        sum_mv += d_mv
        sum_m += d_m
        sum_old += d_old
    node = key + (o[0] * n_grid + o[1]) * n_grid + o[2]
    return node, sum_mv, sum_m, sum_old


@wp.func
def window_sums(t_key: Any, t_end: Any, t_runs: Any, runs: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any, t_mC: Any,
                lane: int, threads: int, n_grid: int, dx: float, affine_flip: int, grid_mv: wp.array(dtype=wp.vec3),
                grid_m: wp.array(dtype=float), grid_mv_old: wp.array(dtype=wp.vec3), records: int,
                sums_mvm: wp.array(dtype=wp.vec4), sums_old: wp.array(dtype=wp.vec4)):
    """A block's sums from its staged terms (shared-memory tiles of the window's slots: key, run
    end (:func:`window_run_end`), the weights ``t_w[slot, 3 axis + node]``, ``fx``, momentum and
    mass, and the rows of ``affine`` and ``m C``, each in a vec4: one 16-byte load where a vec3
    or a matrix's row would take three) and its ``runs`` runs' first slots ``t_runs`` (in slot
    order): the thread ``lane`` of ``threads`` takes the (run, stencil node) pairs ``lane, lane + threads,
    ...``; a run is the slots ``s .. t_end[s] - 1``, its :func:`node_term` summed to node ``n`` in
    slot order (:func:`window_run_sum`), and added to the grid
    (flat arrays of the ``n_grid``^3 nodes; a base cell's key is its node's index) with one
    atomic per array, or (``records = 1``) to the node records ``sums_mvm`` and ``sums_old``
    with one :func:`vec4_atomic_add` each."""
    for q in range(lane, runs * 27, threads):
        node, sum_mv, sum_m, sum_old = window_run_sum(t_key, t_end, t_runs, q, t_w, t_fx, t_mv, t_aff, t_mC, n_grid, dx,
                                                      affine_flip)
        if records == 1:
            vec4_atomic_add(sums_mvm, node, wp.vec4(sum_mv[0], sum_mv[1], sum_mv[2], sum_m))
            if affine_flip == 1:
                vec4_atomic_add(sums_old, node, wp.vec4(sum_old[0], sum_old[1], sum_old[2], 0.0))
        else:
            wp.atomic_add(grid_mv, node, sum_mv)
            wp.atomic_add(grid_m, node, sum_m)
            if affine_flip == 1:
                wp.atomic_add(grid_mv_old, node, sum_old)


@wp.func
def window_sums_fixed(t_key: Any, t_end: Any, t_runs: Any, runs: int, t_w: Any, t_fx: Any, t_mv: Any, t_aff: Any,
                      t_mC: Any, lane: int, threads: int, n_grid: int, dx: float, affine_flip: int,
                      q_sums: wp.array2d(dtype=wp.int64), scale_m: float, scale_p: float,
                      overflow: wp.array(dtype=wp.int32)):
    """:func:`window_sums` into the fixed-point sums ``q_sums`` (:func:`fixed_add`; mass in
    units of ``1 / scale_m``, momenta of ``1 / scale_p``): the same run sums, added in integers,
    so the nodes' sums do not depend on the order the runs arrive in."""
    for q in range(lane, runs * 27, threads):
        node, sum_mv, sum_m, sum_old = window_run_sum(t_key, t_end, t_runs, q, t_w, t_fx, t_mv, t_aff, t_mC, n_grid, dx,
                                                      affine_flip)
        for a in range(3):
            fixed_add(q_sums, a, node, sum_mv[a], scale_p, overflow)
        fixed_add(q_sums, 3, node, sum_m, scale_m, overflow)
        if affine_flip == 1:
            for a in range(3):
                fixed_add(q_sums, 4 + a, node, sum_old[a], scale_p, overflow)


@wp.func
def vec4_head(a: wp.vec4) -> wp.vec3:
    """The first three components of ``a``."""
    return wp.vec3(a[0], a[1], a[2])


@wp.func
def mat33_from_rows(r0: wp.vec4, r1: wp.vec4, r2: wp.vec4) -> wp.mat33:
    """The matrix whose rows are the first three components of ``r0``, ``r1``, ``r2``."""
    return wp.mat33(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2])


@wp.func
def window_runs_before(t_end: Any, s: int, window: int) -> wp.vec2i:
    """How many runs start before slot ``s`` of a window (slots whose run end is not 0), and in
    the whole window."""
    before = int(0)
    total = int(0)
    for t in range(window):
        if t_end[t] != 0:
            if t < s:
                before += 1
            total += 1
    return wp.vec2i(before, total)


@wp.func_native("""#if defined(__CUDA_ARCH__)
const unsigned m = __ballot_sync(0xffffffffu, starts != 0);
return wp::vec2i(__popc(m & ((1u << (threadIdx.x & 31u)) - 1u)), __popc(m));
#else
return wp::vec2i(-1, -1);
#endif
""")
def warp_runs_before(starts: int) -> wp.vec2i:
    """:func:`window_runs_before` for a window of 32 slots held by one warp, a slot a lane
    (``starts``: a run starts at this lane's slot): the runs that start at the lanes below this
    one, and in the whole warp, from one ballot. ``(-1, -1)`` on the CPU, whose block is one
    thread (the caller counts there)."""
    ...


@wp.func_native("""#if defined(__CUDA_ARCH__)
const unsigned m = __ballot_sync(0xffffffffu, change != 0);
const unsigned lane = threadIdx.x & 31u;
if (!start) return 0;
const unsigned above = lane == 31u ? 0u : (m >> (lane + 1u));
return above ? (int)(lane + __ffs(above)) : 32;
#else
return -1;
#endif
""")
def warp_run_end(change: int, start: int) -> int:
    """:func:`window_run_end` for a window of 32 slots held by one warp, a slot a lane
    (``change``: this slot's key differs from the slot before's, or it is the first;
    ``start``: a run starts here): the next lane above whose key changes, or 32, from one
    ballot; 0 where no run starts. -1 on the CPU (the caller searches there)."""
    ...


@wp.func
def window_run_end(t_key: Any, s: int, window: int, none_key: int) -> int:
    """The end (one past the last slot) of the run of equal keys that starts at slot ``s`` of a
    window's staged keys, or 0 where no run starts there (the slot before holds the same key,
    or the slot is empty: ``none_key``). Found once per slot, not once per stencil node."""
    key = t_key[s]
    if key == none_key:
        return 0
    if s > 0:
        if t_key[s - 1] == key:
            return 0
    e = s + 1
    while e < window:
        if t_key[e] != key:
            break
        e += 1
    return e


_WINDOW_KERNELS: dict = {}


def p2g_windows(window: int, affine_flip: int, fixed: bool = False, records: bool = False):
    """The P2G-by-windows kernel for windows of ``window`` sorted positions under the transfer
    ``affine_flip`` (1: affine FLIP, 0: APIC). A tile's size is fixed when the kernel is
    compiled, and the transfer is made a constant of the kernel (its branches in the inner
    loop compiled away), so one kernel per size and transfer. Launch with
    ``wp.launch_tiled(..., dim=ceil(count / window), block_dim=window)``; the CPU runs it with
    one thread a block (the loops stride by the block's size), the same sums. ``fixed``: the
    run sums go into the fixed-point sums ``q`` (:func:`window_sums_fixed`) instead of the
    float grid arrays (each variant ignores the other's arguments); ``records``: into the node
    records ``sums_mvm`` and ``sums_old`` with vector atomics (:func:`vec4_atomic_add`)."""
    if fixed and records:
        raise ValueError("the window sums go into the fixed-point sums or the node records, not both")
    kernel = _WINDOW_KERNELS.get((window, affine_flip, fixed, records))
    if kernel is not None:
        return kernel

    def p2g_windows_kernel(
        order: wp.array(dtype=wp.int32),
        keys: wp.array(dtype=wp.int32),
        none_key: int,
        count: int,
        n_grid: int,
        inv_dx: float,
        fx: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        mass: wp.array(dtype=float),
        affine: Any,
        C: Any,
        grid_mv: wp.array(dtype=wp.vec3),
        grid_m: wp.array(dtype=float),
        grid_mv_old: wp.array(dtype=wp.vec3),
        sums_mvm: wp.array(dtype=wp.vec4),
        sums_old: wp.array(dtype=wp.vec4),
        q_sums: wp.array2d(dtype=wp.int64),
        scale_m: float,
        scale_p: float,
        overflow: wp.array(dtype=wp.int32),
    ):
        """Block ``b`` stages the terms of the particles ``order[b W + slot]`` (slot
        ``0 .. W-1``; past ``count``: key ``none_key``) in shared memory, the B-spline weights
        of each (the node's weight is then three loads and two products), and sums them
        (:func:`window_sums`)."""
        b, lane = wp.tid()
        threads = wp.block_dim()
        s0 = b * wp.static(window)
        t_key = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        t_w = wp.tile_empty(shape=(wp.static(window), 9), dtype=float, storage="shared")
        t_fx = wp.tile_empty(shape=wp.static(window), dtype=wp.vec4, storage="shared")
        t_mv = wp.tile_empty(shape=wp.static(window), dtype=wp.vec4, storage="shared")
        t_aff = wp.tile_empty(shape=(wp.static(window), 3), dtype=wp.vec4, storage="shared")
        t_mC = wp.tile_empty(shape=(wp.static(window), 3), dtype=wp.vec4, storage="shared")
        for slot in range(lane, wp.static(window), threads):
            key = none_key
            p = int(0)
            if s0 + slot < count:
                p = order[s0 + slot]
                key = keys[p]
            q = momentum_mass(v, mass, p)
            f = fx[p]
            W = bspline_weights(f)
            wp.tile_scatter_masked(t_key, slot, key, True)
            for a in range(3):
                for n in range(3):
                    wp.tile_scatter_masked(t_w, slot, 3 * a + n, W[n, a], True)
            wp.tile_scatter_masked(t_fx, slot, wp.vec4(f[0], f[1], f[2], 0.0), True)
            wp.tile_scatter_masked(t_mv, slot, q, True)
            A = mat33_at(affine, p)
            for r in range(3):
                wp.tile_scatter_masked(t_aff, slot, r, wp.vec4(A[r, 0], A[r, 1], A[r, 2], 0.0), True)
            if wp.static(affine_flip == 1):
                M = apic_term(q, C, p)
                for r in range(3):
                    wp.tile_scatter_masked(t_mC, slot, r, wp.vec4(M[r, 0], M[r, 1], M[r, 2], 0.0), True)
        t_end = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        for slot in range(lane, wp.static(window), threads):
            e = int(-1)
            if wp.static(window == 32):  # a warp a window on a GPU: the run ends found by a ballot
                key = t_key[slot]
                change = int(1)
                if slot > 0:
                    change = int(t_key[slot - 1] != key)
                e = warp_run_end(change, int(change == 1 and key != none_key))
            if e < 0:
                e = window_run_end(t_key, slot, wp.static(window), none_key)
            wp.tile_scatter_masked(t_end, slot, e, True)
        # the runs' first slots listed in slot order, so the threads share out (run, node) pairs only
        t_runs = wp.tile_empty(shape=wp.static(window), dtype=wp.int32, storage="shared")
        runs = int(0)
        for slot in range(lane, wp.static(window), threads):
            ranks = wp.vec2i(-1, -1)
            if wp.static(window == 32):  # a warp a window on a GPU: the runs counted by a ballot
                ranks = warp_runs_before(int(t_end[slot] != 0))
            if ranks[0] < 0:
                ranks = window_runs_before(t_end, slot, wp.static(window))
            wp.tile_scatter_masked(t_runs, ranks[0], slot, t_end[slot] != 0)
            runs = ranks[1]
        if wp.static(fixed):
            window_sums_fixed(t_key, t_end, t_runs, runs, t_w, t_fx, t_mv, t_aff, t_mC, lane, threads, n_grid,
                              1.0 / inv_dx, wp.static(affine_flip), q_sums, scale_m, scale_p, overflow)
        else:
            window_sums(t_key, t_end, t_runs, runs, t_w, t_fx, t_mv, t_aff, t_mC, lane, threads, n_grid, 1.0 / inv_dx,
                        wp.static(affine_flip), grid_mv, grid_m, grid_mv_old, wp.static(int(records)), sums_mvm, sums_old)

    name = (f"p2g_windows_{window}_{'affine_flip' if affine_flip == 1 else 'apic'}{'_fixed' if fixed else ''}"
            f"{'_records' if records else ''}")
    kernel = overload_per_layout(wp.Kernel(p2g_windows_kernel, key=name, module=wp.get_module(__name__)),
                                 f32=("affine", "C"))
    _WINDOW_KERNELS[window, affine_flip, fixed, records] = kernel
    return kernel


@wp.func
def gather_by_nodes(grid_v: wp.array(dtype=wp.vec3), grid_v_old: wp.array(dtype=wp.vec3), origin: int, n_grid: int,
                    fx: wp.vec3, inv_dx: float, affine_flip: int):
    """G2P's gather, node by node: the velocity ``sum w v`` [m/s] and affine matrix ``4 / dx sum w
    v (x_i - x_p)^T`` [1/s] from the node velocities ``grid_v`` (flat arrays of the ``n_grid``^3
    grid, the stencil's first node at ``origin``) for the position ``fx`` in the base cell
    [cells]; with ``affine_flip = 1`` the same sums of the increments ``grid_v - grid_v_old``
    too (zero otherwise). An outer product a node: 54 multiply-adds a node under affine FLIP."""
    w = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    dv = wp.vec3(0.0)
    dC = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                dpos = wp.vec3(float(i), float(j), float(k)) - fx
                node = origin + (i * n_grid + j) * n_grid + k
                gv = grid_v[node]
                new_v = new_v + weight * gv
                new_C = new_C + (4.0 * inv_dx * weight) * wp.outer(gv, dpos)
                if affine_flip == 1:
                    du = gv - grid_v_old[node]
                    dv = dv + weight * du
                    dC = dC + (4.0 * inv_dx * weight) * wp.outer(du, dpos)
    return new_v, new_C, dv, dC


@wp.func
def columns_to_mat33(c0: wp.vec3, c1: wp.vec3, c2: wp.vec3, scale: float) -> wp.mat33:
    """The matrix of columns ``scale c0``, ``scale c1``, ``scale c2``."""
    return scale * wp.mat33(c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])


@wp.func
def fold_line(v: wp.vec3, c0: wp.vec3, c1: wp.vec3, c2: wp.vec3, line_w: wp.vec3, line_d: wp.vec3, wi: float,
              wj: float, di: float, dj: float):
    """Add a stencil line's sums (``line_w``: weighted by ``w_z``, ``line_d``: by ``w_z d_z``) to
    the gather's velocity and affine columns, with the line's x and y weights ``wi``, ``wj``
    and their offset-weighted ``di = wi d_x``, ``dj = wj d_y`` (:func:`gather_by_lines`)."""
    wij = wi * wj
    return v + wij * line_w, c0 + (di * wj) * line_w, c1 + (wi * dj) * line_w, c2 + wij * line_d


@wp.func
def gather_by_lines(grid_v: wp.array(dtype=wp.vec3), grid_v_old: wp.array(dtype=wp.vec3), origin: int, n_grid: int,
                    fx: wp.vec3, inv_dx: float, affine_flip: int):
    """:func:`gather_by_nodes`'s sums factored along the stencil's lines. The weight and the
    offset ``x_i - x_p`` of a node are products over the axes, so column ``a`` of the affine
    matrix is ``sum w_x w_y w_z d_a v`` with ``d_a = (o_a - fx_a)`` taken into axis ``a``'s
    weight: a line of three nodes along z is summed with the weights ``w_z`` and ``w_z d_z``
    (six multiply-adds a node), and the two line sums then enter the four sums with the line's
    x and y weights (twelve a line): ~300 multiply-adds a particle and field instead of ~700.
    The same sums in another order (float rounding apart)."""
    w = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    c0 = wp.vec3(0.0)
    c1 = wp.vec3(0.0)
    c2 = wp.vec3(0.0)
    dv = wp.vec3(0.0)
    e0 = wp.vec3(0.0)
    e1 = wp.vec3(0.0)
    e2 = wp.vec3(0.0)
    for i in range(3):
        wi = w[i, 0]
        di = wi * (float(i) - fx[0])
        for j in range(3):
            wj = w[j, 1]
            dj = wj * (float(j) - fx[1])
            row = origin + (i * n_grid + j) * n_grid
            line_v = wp.vec3(0.0)
            line_d = wp.vec3(0.0)
            line_dv = wp.vec3(0.0)
            line_dd = wp.vec3(0.0)
            for k in range(3):
                wk = w[k, 2]
                dk = wk * (float(k) - fx[2])
                gv = grid_v[row + k]
                line_v = line_v + wk * gv
                line_d = line_d + dk * gv
                if affine_flip == 1:
                    du = gv - grid_v_old[row + k]
                    line_dv = line_dv + wk * du
                    line_dd = line_dd + dk * du
            new_v, c0, c1, c2 = fold_line(new_v, c0, c1, c2, line_v, line_d, wi, wj, di, dj)
            if affine_flip == 1:
                dv, e0, e1, e2 = fold_line(dv, e0, e1, e2, line_dv, line_dd, wi, wj, di, dj)
    return new_v, columns_to_mat33(c0, c1, c2, 4.0 * inv_dx), dv, columns_to_mat33(e0, e1, e2, 4.0 * inv_dx)


@wp.func
def g2p_particle(
    p: int,
    grid_v: wp.array(dtype=wp.vec3),
    n_grid: int,
    inv_dx: float,
    dt: float,
    trans_mask: wp.array(dtype=wp.int32),
    trans_velocity: wp.vec3,
    trans_on: int,
    lo: wp.vec3i,
    hi: wp.vec3i,
    x0: wp.array(dtype=wp.vec3),
    affine_flip: int,
    flip_weight: float,
    grid_v_old: wp.array(dtype=wp.vec3),
    g2p_lines: int,
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    overrun: wp.array(dtype=wp.int32),
):
    """Particle ``p``'s G2P (see :func:`g2p`), written back; returns whether its stencil lay
    inside the active box and the new displacement, velocity, affine matrix and F. The node
    velocities ``grid_v`` and ``grid_v_old`` are read as flat arrays of the (``n_grid``)^3 grid
    (node ``(i, j, k)`` at ``(i n_grid + j) n_grid + k``): one index a node from the stencil's
    first, instead of three with their checks. ``g2p_lines = 1`` gathers by stencil lines
    (:func:`gather_by_lines`), 0 node by node (:func:`gather_by_nodes`)."""
    up = u[p]
    gx = (x0[p] + up) * inv_dx
    base = stencil_base(gx)
    if not stencil_inside(base, lo, hi):
        wp.atomic_add(overrun, 0, 1)
        return False, up, v[p], mat33_at(C, p), mat33d_at(F, p)
    fx = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    origin = (base[0] * n_grid + base[1]) * n_grid + base[2]
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    dv = wp.vec3(0.0)
    dC = wp.mat33(0.0)
    if g2p_lines == 1:
        new_v, new_C, dv, dC = gather_by_lines(grid_v, grid_v_old, origin, n_grid, fx, inv_dx, affine_flip)
    else:
        new_v, new_C, dv, dC = gather_by_nodes(grid_v, grid_v_old, origin, n_grid, fx, inv_dx, affine_flip)
    held = trans_on == 1 and trans_mask[p] != 0
    if held:  # a prescribed motion: v and C take it exactly, under either transfer
        new_v = trans_velocity
        new_C = wp.mat33(0.0)
    Fp = (wp.identity(n=3, dtype=wp.float64) + wp.float64(dt) * mat33_to_f64(new_C)) * mat33d_at(F, p)
    mat33d_put(F, p, Fp)
    up = up + dt * new_v
    u[p] = up
    vp = new_v
    Cp = new_C
    if affine_flip == 1 and not held:
        vp = flip_weight * (v[p] + dv) + (1.0 - flip_weight) * new_v
        Cp = flip_weight * (mat33_at(C, p) + dC) + (1.0 - flip_weight) * new_C
    v[p] = vp
    mat33_put(C, p, Cp)
    return True, up, vp, Cp, Fp


@wp.kernel(cuda_max_registers=CUDA_MAX_REGISTERS)
def g2p(
    grid_v: wp.array(dtype=wp.vec3),
    n_grid: int,
    inv_dx: float,
    dt: float,
    trans_mask: wp.array(dtype=wp.int32),
    trans_velocity: wp.vec3,
    trans_on: int,
    lo: wp.vec3i,
    hi: wp.vec3i,
    x0: wp.array(dtype=wp.vec3),
    affine_flip: int,
    flip_weight: float,
    grid_v_old: wp.array(dtype=wp.vec3),
    g2p_lines: int,
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: Any,
    F: Any,
    overrun: wp.array(dtype=wp.int32),
):
    """Gather (node velocities as flat arrays of the ``n_grid``^3 grid): new velocity and
    affine matrix (APIC, or with ``affine_flip = 1`` the affine FLIP update of weight
    ``flip_weight = exp(-dt / tau)`` with the old node velocities
    ``grid_v_old`` [m/s]), F <- (I + dt C_pic) F (F in float64), advect with the grid velocity
    ``v_pic``.

    Positions are rest position ``x0`` plus displacement ``u``; advecting the (small)
    displacement keeps sub-ulp motion that ``x += dt v`` in float32 near x = 1 would round
    away (a creep or a freeze of one ulp per substep)."""
    p = wp.tid()
    g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo, hi, x0, affine_flip,
                 flip_weight, grid_v_old, g2p_lines, u, v, C, F, overrun)


_G2P_PREPARE_KERNELS: dict = {}


def g2p_prepare(affine_flip: int) -> wp.Kernel:
    """The fused G2P kernel (:func:`g2p` with the next substep's :func:`p2g_prepare`) under the
    transfer ``affine_flip`` (1: affine FLIP, 0: APIC), made a constant of the kernel, as the
    windows' kernels are: APIC's kernel then holds neither the old node velocities' sums nor
    their registers. One kernel per transfer, its overloads per matrix layout made with it."""
    kernel = _G2P_PREPARE_KERNELS.get(affine_flip)
    if kernel is not None:
        return kernel

    def g2p_prepare_kernel(
        grid_v: wp.array(dtype=wp.vec3),
        inv_dx: float,
        dt: float,
        trans_mask: wp.array(dtype=wp.int32),
        trans_velocity: wp.vec3,
        trans_on: int,
        lo: wp.vec3i,
        hi: wp.vec3i,
        x0: wp.array(dtype=wp.vec3),
        flip_weight: float,
        grid_v_old: wp.array(dtype=wp.vec3),
        g2p_lines: int,
        mass: wp.array(dtype=float),
        vol: wp.array(dtype=float),
        mu: wp.array(dtype=float),
        lam: wp.array(dtype=float),
        probe_mask: wp.array(dtype=wp.int32),
        probe_force: wp.vec3,
        probe_on: int,
        polar_iters: int,
        polar_step: float,
        polar_rational: int,
        retardation: float,
        n_grid: int,
        none_key: int,
        u: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: Any,
        F: Any,
        rot: wp.array(dtype=wp.quat),
        fx: wp.array(dtype=wp.vec3),
        affine: Any,
        keys: wp.array(dtype=wp.int32),
        overrun: wp.array(dtype=wp.int32),
    ):
        """:func:`g2p` fused with the next substep's :func:`p2g_prepare` (its probe state
        ``probe_on``): the new velocity, affine matrix, F and position go from registers into
        the next P2G terms instead of being read back. The same arithmetic as the two kernels
        in turn, so the same bits."""
        p = wp.tid()
        ok, up, vp, Cp, Fp = g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo, hi,
                                          x0, wp.static(affine_flip), flip_weight, grid_v_old, g2p_lines, u, v, C, F,
                                          overrun)
        if ok:
            m = mass[p]
            if probe_on == 1 and probe_mask[p] != 0:
                vp = vp + probe_force * (dt / m)
                v[p] = vp
            q, aff, mCp = p2g_terms(vp, Cp, Fp, rot[p], m, vol[p], mu[p], lam[p], inv_dx, dt, polar_iters, polar_step,
                                    polar_rational, retardation)
            rot[p] = q
            p2g_store(p, (x0[p] + up) * inv_dx, aff, lo, hi, n_grid, none_key, fx, affine, keys, overrun)
        else:
            keys[p] = none_key

    name = f"g2p_prepare_{'affine_flip' if affine_flip == 1 else 'apic'}"
    kernel = overload_per_layout(wp.Kernel(g2p_prepare_kernel, key=name, module=wp.get_module(__name__),
                                           options={"cuda_max_registers": CUDA_MAX_REGISTERS}),
                                 f32=("C", "affine"), f64=("F",))
    _G2P_PREPARE_KERNELS[affine_flip] = kernel
    return kernel


@wp.kernel
def gather_positions(x0: wp.array(dtype=wp.vec3), u: wp.array(dtype=wp.vec3), index: wp.array(dtype=wp.int32),
                     out: wp.array(dtype=wp.vec3)):
    """Export row ``i``: the position x0 + u of particle ``index[i]`` [m]."""
    i = wp.tid()
    p = index[i]
    out[i] = x0[p] + u[p]


@wp.kernel
def gather_F(F: Any, index: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.mat33)):
    """Export row ``i``: the deformation gradient of particle ``index[i]``, in float32."""
    i = wp.tid()
    out[i] = mat33_to_f32(mat33d_at(F, index[i]))


#: particles a block of the guard's statistics covers (its threads stride over them)
STATS_PER_BLOCK = 1024
#: threads a block of the guard's statistics (on a GPU; the CPU runs one a block)
STATS_BLOCK_DIM = 256


@wp.kernel
def guard_reset(out_f: wp.array(dtype=float), out_i: wp.array(dtype=wp.int32)):
    """The guard statistics' starting values (see :func:`particle_stats`), set on the device."""
    big = int(2147483647)
    out_f[0] = 0.0
    out_f[1] = wp.inf
    for a in range(3):
        out_i[1 + a] = big
        out_i[4 + a] = -big
    out_i[0] = 0
    out_i[7] = 0
    out_i[8] = 0


@wp.kernel
def particle_stats(
    x0: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    F: Any,
    inv_dx: float,
    count: int,
    per_block: int,
    overrun: wp.array(dtype=wp.int32),
    overflow: wp.array(dtype=wp.int32),
    out_f: wp.array(dtype=float),
    out_i: wp.array(dtype=wp.int32),
):
    """Guard statistics of the particles ``b per_block .. (b + 1) per_block - 1`` in block
    ``b`` (its threads stride over them, then the block reduces its threads' values: one atomic
    a block and statistic, not one a particle, on a single address): out_f[0] = max |v|^2
    [m^2/s^2], out_f[1] = min det F; out_i[0] = non-finite count, out_i[1:4] = min cell,
    out_i[4:7] = max cell, and from block 0 the G2P overrun flag ``overrun[0]`` in out_i[7]
    and the reproducible P2G's ``overflow[0]`` in out_i[8] (one read-back for all). Maxima,
    minima and counts: the same values in any order. Start from :func:`guard_reset`; launch
    tiled over ``ceil(count / per_block)`` blocks."""
    b, lane = wp.tid()
    threads = wp.block_dim()
    big = int(2147483647)
    v2 = float(0.0)
    det = float(wp.inf)
    bad = int(0)
    lo0 = big
    lo1 = big
    lo2 = big
    hi0 = -big
    hi1 = -big
    hi2 = -big
    for p in range(b * per_block + lane, wp.min((b + 1) * per_block, count), threads):
        xp = x0[p] + u[p]
        vp = v[p]
        Fp = mat33_to_f32(mat33d_at(F, p))
        s = xp[0] + xp[1] + xp[2] + vp[0] + vp[1] + vp[2]
        for a in range(3):
            for c in range(3):
                s = s + Fp[a, c]
        if not wp.isfinite(s):
            bad += 1
            continue
        v2 = wp.max(v2, wp.dot(vp, vp))
        det = wp.min(det, wp.determinant(Fp))
        c0 = int(wp.floor(xp[0] * inv_dx))
        c1 = int(wp.floor(xp[1] * inv_dx))
        c2 = int(wp.floor(xp[2] * inv_dx))
        lo0 = wp.min(lo0, c0)
        lo1 = wp.min(lo1, c1)
        lo2 = wp.min(lo2, c2)
        hi0 = wp.max(hi0, c0)
        hi1 = wp.max(hi1, c1)
        hi2 = wp.max(hi2, c2)
    t_v2 = wp.tile_max(wp.tile(v2))
    t_det = wp.tile_min(wp.tile(det))
    t_bad = wp.tile_sum(wp.tile(bad))
    t_lo0 = wp.tile_min(wp.tile(lo0))
    t_lo1 = wp.tile_min(wp.tile(lo1))
    t_lo2 = wp.tile_min(wp.tile(lo2))
    t_hi0 = wp.tile_max(wp.tile(hi0))
    t_hi1 = wp.tile_max(wp.tile(hi1))
    t_hi2 = wp.tile_max(wp.tile(hi2))
    if lane == 0:
        wp.atomic_max(out_f, 0, t_v2[0])
        wp.atomic_min(out_f, 1, t_det[0])
        if t_bad[0] > 0:
            wp.atomic_add(out_i, 0, t_bad[0])
        wp.atomic_min(out_i, 1, t_lo0[0])
        wp.atomic_min(out_i, 2, t_lo1[0])
        wp.atomic_min(out_i, 3, t_lo2[0])
        wp.atomic_max(out_i, 4, t_hi0[0])
        wp.atomic_max(out_i, 5, t_hi1[0])
        wp.atomic_max(out_i, 6, t_hi2[0])
        if b == 0:
            out_i[7] = overrun[0]
            out_i[8] = overflow[0]


# the kernels generic in the matrices' layout, with their overloads (see overload_per_layout;
# the windows' kernel gets its own where it is made)
overload_per_layout(state_rest, f64=("F",))
overload_per_layout(p2g, f32=("C",), f64=("F",))
overload_per_layout(p2g_prepare, f32=("C", "affine"), f64=("F",))
overload_per_layout(g2p, f32=("C",), f64=("F",))
for _flip in (0, 1):
    g2p_prepare(_flip)
overload_per_layout(gather_F, f64=("F",))
overload_per_layout(particle_stats, f64=("F",))
