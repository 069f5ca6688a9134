"""Grid kernels of the solver, launched over the active box: zeroing, the grid update (from the
grid's arrays, from the fixed-point sums or from the vector-atomic node records) and the
boundary conditions (domain walls, held supports), with the fixed-point and vector atomics
that P2G adds its sums with."""

from __future__ import annotations

import warp as wp

from ._math import vec4_head
from . import _module
from ._module import MODULE


@wp.kernel(module=MODULE)
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


@wp.func(module=MODULE)
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


@wp.func(module=MODULE)
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


@wp.kernel(module=MODULE)
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


@wp.func(module=MODULE)
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


@wp.func(module=MODULE)
def fixed_value(q: wp.array2d(dtype=wp.int64), row: int, node: int, unit: wp.float64) -> float:
    """The fixed-point sum ``q[row, node]`` as a float (``unit`` = 1 / scale)."""
    return float(wp.float64(q[row, node]) * unit)


@wp.kernel(module=MODULE)
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
@_module.func_native("""#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
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


@wp.kernel(module=MODULE)
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


@wp.kernel(module=MODULE)
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


#: a node within this share of a cell of a support box's face lies on it. The box is closed, and a
#: face on a node plane stays there in float32: the node's position ``k * dx - center`` rounds to
#: either side of the face (the Vasedeck's top at n_grid 100, node 37, fell outside; the paper
#: Pillow's x faces, nodes 15 and 85, one in and one out)
FACE_TOLERANCE = wp.constant(1.0e-3)


@wp.func(module=MODULE)
def inside_box(p: wp.vec3, half_size: wp.vec3) -> bool:
    """Whether ``p`` (relative to a box's centre) lies in the closed box."""
    return wp.abs(p[0]) <= half_size[0] and wp.abs(p[1]) <= half_size[1] and wp.abs(p[2]) <= half_size[2]


@wp.func(module=MODULE)
def node_in_box(p: wp.vec3, half_size: wp.vec3, dx: float) -> bool:
    """Whether a grid node at ``p`` (relative to a box's centre) [m] lies in the closed box, a
    node within :data:`FACE_TOLERANCE` cells of a face counted on it."""
    slack = FACE_TOLERANCE * dx
    return inside_box(p, half_size + wp.vec3(slack, slack, slack))


@wp.func(module=MODULE)
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


@wp.kernel(module=MODULE)
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
    if node_in_box(p, half_size, dx):
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


