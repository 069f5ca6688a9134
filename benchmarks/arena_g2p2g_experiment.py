"""An experiment, not a solver path: G2P fused with the next substep's P2G, each block's P2G
summed into a node arena in shared memory before one atomic per arena node.

The solver's GPU substep runs G2P fused with the next P2G's per-particle half (``g2p_prepare``,
which stores each particle's P2G terms: ~50 bytes a particle written, ~110 read back) and then
sums the terms by windows of 32 sorted particles (``p2g_windows``: one global atomic per run of
equal base cells, stencil node and sum; ~24 a particle on the 8-a-cell block). Here one kernel
(``g2p2g_arena``) does both, as the GPU MPM literature's G2P2G does over grid blocks:

- the particles are held in grid-block order (``--tile`` cells a side, then the cells within
  a block; ``block_order``), so a CUDA block's ``--block`` consecutive particles lie in one or
  two grid blocks;
- a thread runs its particle's G2P (the node velocities read from the global grid) and its
  next P2G terms in registers;
- the block reduces its particles' stencil base cells to a bounding box; where the box's nodes
  fit the arena (``--cap`` nodes), each thread adds its 27 stencil contributions to the arena
  in shared memory, and the block then adds each arena node that received mass to the next
  grid with one atomic per sum; a block whose box does not fit adds its particles'
  contributions to the grid directly (counted: ``spilled``).

How the block sums into its arena (``--arena``): ``tiles``, Warp's ``tile_scatter_add`` (a
block barrier after every scatter, the box by tile reductions); ``atomics``, float shared
atomics on a ``__shared__`` array of CUDA snippets (``wp.func_native``: ``arena_address``,
``arena_add``, ``block_sync``; three barriers a block, the box by shared ``atomicMin`` /
``atomicMax``); ``fixed``, int64 shared atomics in the reproducible P2G's fixed-point units,
converted back to floats at the flush. ``--interleave G`` orders each grid block's cells in
groups of G and, within a group, every cell's first particle, then every cell's second, ..., so
a warp's lanes lie in different cells and its shared atomics on one stencil node go to
different addresses. ``--rotate 1`` does that in cell order instead: each particle visits its
stencil nodes from node ``p mod 27`` on. ``--box warp`` reduces the box in each warp first.
``--regs`` caps the kernel's registers, ``--merge-zero`` zeroes the other grids in the grid
update's pass, and the environment's ``ARENA_SUM_FLOATS`` sizes the shared arena (its size
bounds the blocks an SM holds).

No stored terms, no sort, no window kernel; the grid is double-buffered (node velocities read
from one set of grids, sums added to another, swapped every substep), so a substep is: zero the
other grids, the grid update and supports, the fused kernel. On the CPU (one lane a block) a
block is one particle (the snippets' arena a static array, their barrier nothing), so the arena
only checks the indexing: there the float arenas give the solver's scatter path bit for bit,
the int64 one to its units' rounding.

Builds the object's model (``block``: ``sim_bench.py``'s 681k jelly block; or a contract's
object), the particles in grid-block order, runs ``--warm`` substeps, then from one saved state
times ``--steps`` substeps of the solver's default GPU path (graphs) and of the experiment at
each block size and arena capacity, ``--repeats`` times, and compares the displacements.

    python3 benchmarks/arena_g2p2g_experiment.py --object block --particles-count 20000 --n-grid 32 --device cpu \
        --warm 20 --steps 10 --repeats 1 --arena tiles atomics fixed --cap 26 512
    python3 benchmarks/arena_g2p2g_experiment.py --object block --device cuda:0 --block 128 256 --cap 512 1024
    python3 benchmarks/arena_g2p2g_experiment.py --object block --device cuda:0 --transfer apic --interleave 64 \
        --arena atomics fixed --block 128 256 --cap 512
    python3 benchmarks/arena_g2p2g_experiment.py --object pillow --profile paper --particles OUT/pillow.npz
    ARENA_SUM_FLOATS=2048 python3 benchmarks/arena_g2p2g_experiment.py --object block --device cuda:0 --transfer apic \
        --interleave 64 --arena atomics --block 128 --cap 512 --regs 64 --merge-zero --steps 500 --repeats 3
"""
import argparse
import os
from typing import Any

import numpy as np
import warp as wp
from _fused_pipeline import FusedPipeline, g2p_next_terms

from knockgs_core.sim._kernels import bspline_weight, bspline_weights, weighted_node_term
from knockgs_core.sim._solver import _FixedScratch

#: floats of the shared-atomics arena: six int bounds (and two spare) and the sums, by default seven a node for up
#: to 1,024 nodes. The array is the block's static shared memory, so its size bounds the blocks an SM holds (29 KB
#: held an H200's SM to 5 blocks of 128): the environment's ``ARENA_SUM_FLOATS`` sizes it for a run
ARENA_FLOATS = 8 + int(os.environ.get("ARENA_SUM_FLOATS", 7 * 1024))


def _native(cuda: str, cpu: str) -> str:
    """A snippet's CUDA body and its CPU body (one lane a block: plain loads and adds)."""
    return f"#if defined(__CUDA_ARCH__)\n{cuda}\n#else\n{cpu}\n#endif\n"


@wp.func_native(_native(f"__shared__ float arena[{ARENA_FLOATS}];\nreturn (uint64_t)(&arena[0]);",
                        f"static float arena[{ARENA_FLOATS}];\nreturn (uint64_t)(&arena[0]);"))
def arena_address() -> wp.uint64:
    """The block's arena in shared memory (a static array on the CPU)."""
    ...


@wp.func_native(_native("atomicAdd(((float*)a) + i, x);", "((float*)a)[i] += x;"))
def arena_add(a: wp.uint64, i: int, x: float):
    """Adds ``x`` to float ``i`` of the arena at ``a`` (a shared atomic on a GPU)."""
    ...


@wp.func_native("return ((float*)a)[i];")
def arena_get(a: wp.uint64, i: int) -> float:
    ...


@wp.func_native("((float*)a)[i] = x;")
def arena_set(a: wp.uint64, i: int, x: float):
    ...


@wp.func_native(_native("atomicMin(((int*)a) + i, x);", "if (x < ((int*)a)[i]) ((int*)a)[i] = x;"))
def arena_min(a: wp.uint64, i: int, x: int):
    ...


@wp.func_native(_native("atomicMax(((int*)a) + i, x);", "if (x > ((int*)a)[i]) ((int*)a)[i] = x;"))
def arena_max(a: wp.uint64, i: int, x: int):
    ...


@wp.func_native(_native("unsigned mask = __activemask();\nint m = __reduce_min_sync(mask, x);\n"
                        "if ((threadIdx.x & 31) == __ffs(mask) - 1) atomicMin(((int*)a) + i, m);",
                        "if (x < ((int*)a)[i]) ((int*)a)[i] = x;"))
def arena_min_warp(a: wp.uint64, i: int, x: int):
    """Int ``i`` of the arena at ``a`` lowered to ``x``: the warp's least ``x`` first (one
    ``redux.sync``), then one shared atomic a warp, so its lanes do not queue on one address."""
    ...


@wp.func_native(_native("unsigned mask = __activemask();\nint m = __reduce_max_sync(mask, x);\n"
                        "if ((threadIdx.x & 31) == __ffs(mask) - 1) atomicMax(((int*)a) + i, m);",
                        "if (x > ((int*)a)[i]) ((int*)a)[i] = x;"))
def arena_max_warp(a: wp.uint64, i: int, x: int):
    """:func:`arena_min_warp`'s maximum."""
    ...


@wp.func_native("return ((int*)a)[i];")
def arena_geti(a: wp.uint64, i: int) -> int:
    ...


@wp.func_native("((int*)a)[i] = x;")
def arena_seti(a: wp.uint64, i: int, x: int):
    ...


@wp.func_native(_native("atomicAdd(((unsigned long long*)a) + i, (unsigned long long)x);",
                        "((long long*)a)[i] += x;"))
def arena_add64(a: wp.uint64, i: int, x: wp.int64):
    """Adds ``x`` to int64 ``i`` of the arena at ``a`` (a shared integer atomic on a GPU)."""
    ...


@wp.func_native("return ((long long*)a)[i];")
def arena_get64(a: wp.uint64, i: int) -> wp.int64:
    ...


@wp.func
def float_sum_add(a: wp.uint64, slot: int, x: float, scale: float):
    """Adds ``x`` to the arena's float sum ``slot`` (after the eight header ints)."""
    arena_add(a, 8 + slot, x)


@wp.func
def float_sum_get(a: wp.uint64, slot: int, scale: float) -> float:
    return arena_get(a, 8 + slot)


@wp.func
def fixed_sum_add(a: wp.uint64, slot: int, x: float, scale: float):
    """Adds ``x`` to the arena's int64 sum ``slot`` (after the header's four int64s) in units of
    ``1 / scale``, rounded to the nearest unit (no overflow check: an experiment)."""
    arena_add64(a, 4 + slot, wp.int64(wp.round(x * scale)))


@wp.func
def fixed_sum_get(a: wp.uint64, slot: int, scale: float) -> float:
    return float(wp.float64(arena_get64(a, 4 + slot)) / wp.float64(scale))


@wp.func_native(_native("__syncthreads();", ""))
def block_sync():
    """A barrier across the CUDA block (nothing on the CPU)."""
    ...


def block_order(X: np.ndarray, dx: float, tile: int, *, interleave: int = 0) -> np.ndarray:
    """A permutation [N] sorting positions ``X`` [m] by the grid block (``tile`` cells a side)
    of their stencil base cell, x-major, then by the base cell within the block, x-major.

    ``interleave`` (cells, 0: off): within a grid block, the cells in groups of that many (in
    the block's cell order), and within a group first every cell's first particle, then every
    cell's second, and so on. With groups of 32 a GPU warp's lanes lie in 32 cells, so its
    shared atomics on one stencil node go to different addresses (in cell order the ~8 lanes of
    a cell add to the same node, one after the other)."""
    base = np.floor(X.astype(np.float64) / dx - 0.5).astype(np.int64)
    blk, cell = base // tile, base % tile
    order = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0], blk[:, 2], blk[:, 1], blk[:, 0]))
    if not interleave:
        return order
    key = np.stack([blk[:, 0], blk[:, 1], blk[:, 2], cell[:, 0], cell[:, 1], cell[:, 2]], 1)[order]
    new_cell = np.r_[True, (key[1:] != key[:-1]).any(1)]
    starts = np.flatnonzero(new_cell)
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    k = key.T
    group = ((k[3] * tile + k[4]) * tile + k[5]) // interleave
    return order[np.lexsort((k[5], k[4], k[3], rank, group, k[2], k[1], k[0]))]


def make_kernel(cap: int, regs: int, affine_flip: int, arena: str = "tiles", scales: tuple = (1.0, 1.0), *,
                rotate: int = 0, warp_box: int = 0):
    """The fused kernel: ``arena`` ``"tiles"`` (Warp's tile_scatter_add), ``"atomics"`` (float
    shared atomics) or ``"fixed"`` (int64 shared atomics in units of 1 / ``scales`` = (mass,
    momentum) scales, converted back to floats at the flush).

    ``rotate`` (shared-atomics arenas): particle ``p`` visits its 27 stencil nodes starting
    from node ``p mod 27`` (in the stencil's x-major order, wrapping), so the lanes of a warp in
    one cell add to 27 different nodes at once instead of queueing on one, with the particles
    kept in cell order (G2P's reads of the node velocities stay coalesced). ``warp_box``: the
    block's box of base cells reduced in each warp first (:func:`arena_min_warp`)."""
    if arena not in ("tiles", "atomics", "fixed"):
        raise SystemExit(f"--arena: unknown {arena!r}")
    tiles, fixed = arena == "tiles", arena == "fixed"
    if tiles and (rotate or warp_box):
        raise SystemExit("--rotate and --box warp take the shared-atomics arenas")
    box_min, box_max = (arena_min_warp, arena_max_warp) if warp_box else (arena_min, arena_max)
    add, get = (fixed_sum_add, fixed_sum_get) if fixed else (float_sum_add, float_sum_get)
    scale_m, scale_p = scales
    sums = 7 if affine_flip == 1 else 4  # an atomics arena's sums a node
    if not tiles and cap * sums * (2 if fixed else 1) > ARENA_FLOATS - 8:
        raise SystemExit(f"--cap: the shared-atomics arena holds {ARENA_FLOATS - 8} floats (ARENA_SUM_FLOATS), "
                         f"{cap} nodes of {sums} {'int64' if fixed else 'float'} sums need more")

    def g2p2g_arena(
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
        count: int,
        u: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: Any,
        F: Any,
        rot: wp.array(dtype=wp.quat),
        overrun: wp.array(dtype=wp.int32),
        spilled: wp.array(dtype=wp.int32),
        grid_mv: wp.array(dtype=wp.vec3),
        grid_m: wp.array(dtype=float),
        grid_mv_old: wp.array(dtype=wp.vec3),
    ):
        # an atomics arena: ints 0-5 the block's box of base cells, then the node sums by
        # component (momentum 0-2, mass 3, stress-free momentum 4-6), ``cap`` nodes a component
        b, lane = wp.tid()
        threads = wp.block_dim()
        p = b * threads + lane
        big = int(1073741824)
        arena = wp.uint64(0)
        if wp.static(not tiles):
            arena = arena_address()
            for idx in range(lane, wp.static(cap * sums * (2 if fixed else 1)), threads):
                arena_set(arena, 8 + idx, 0.0)
            for d in range(lane, 3, threads):
                arena_seti(arena, d, big)
                arena_seti(arena, 3 + d, -big)
            block_sync()
        valid, base, f, mvp, m, aff, mCp = g2p_next_terms(p, count, grid_v, inv_dx, dt, trans_mask, trans_velocity,
                                                          trans_on, lo, hi, x0, wp.static(affine_flip), flip_weight,
                                                          grid_v_old, g2p_lines, mass, vol, mu, lam, probe_mask,
                                                          probe_force, probe_on, polar_iters, polar_step, polar_rational,
                                                          retardation, n_grid, u, v, C, F, rot, overrun)
        # the block's box of base cells: origin o, extent e (nodes)
        o = wp.vec3i(0)
        e = wp.vec3i(0)
        if wp.static(tiles):
            lo_p = wp.vec3i(big)
            hi_p = wp.vec3i(-big)
            if valid:
                lo_p = base
                hi_p = base
            for d in range(3):
                o[d] = wp.tile_min(wp.tile(lo_p[d]))[0]
                e[d] = wp.tile_max(wp.tile(hi_p[d]))[0] - o[d] + 3
        else:
            if wp.static(warp_box):  # every lane takes part in its warp's reduction
                for d in range(3):
                    box_min(arena, d, wp.where(valid, base[d], big))
                    box_max(arena, 3 + d, wp.where(valid, base[d], -big))
            elif valid:
                for d in range(3):
                    box_min(arena, d, base[d])
                    box_max(arena, 3 + d, base[d])
            block_sync()
            for d in range(3):
                o[d] = arena_geti(arena, d)
                e[d] = arena_geti(arena, 3 + d) - o[d] + 3
        dx = 1.0 / inv_dx
        any_valid = e[0] > 0
        fits = any_valid and e[0] * e[1] * e[2] <= wp.static(cap)
        w = bspline_weights(f)
        q4 = wp.vec4(mvp[0], mvp[1], mvp[2], m)  # momentum and mass, as the solver's node terms take them
        sp = float(wp.static(scale_p))
        sm = float(wp.static(scale_m))
        if wp.static(tiles):
            a_mv = wp.tile_zeros(shape=wp.static(cap), dtype=wp.vec4, storage="shared")
            a_old = wp.tile_zeros(shape=wp.static(cap), dtype=wp.vec3, storage="shared")
        start = int(0)
        if wp.static(rotate):
            start = p % 27
        for i in range(3):  # unrolled; rotated, node (i, j, k) of the loop is node n of the stencil
            for j in range(3):
                for k in range(3):
                    wt = w[i, 0] * w[j, 1] * w[k, 2]
                    ii, jj, kk = i, j, k
                    if wp.static(rotate):
                        n = (start + (i * 3 + j) * 3 + k) % 27
                        ii, jj, kk = n // 9, (n // 3) % 3, n % 3
                        wt = bspline_weight(f[0], ii) * bspline_weight(f[1], jj) * bspline_weight(f[2], kk)
                    a, am, old = weighted_node_term(wt, f, q4, aff, mCp, ii, jj, kk, dx, wp.static(affine_flip))
                    idx = ((base[0] + ii - o[0]) * e[1] + (base[1] + jj - o[1])) * e[2] + (base[2] + kk - o[2])
                    if wp.static(tiles):
                        if fits:  # every thread of the block takes part in a tile's scatter
                            wp.tile_scatter_add(a_mv, idx, wp.vec4(a[0], a[1], a[2], am), valid)
                            if wp.static(affine_flip == 1):
                                wp.tile_scatter_add(a_old, idx, old, valid)
                    elif valid and fits:
                        for c in range(3):
                            wp.static(add)(arena, idx + c * wp.static(cap), a[c], sp)
                        wp.static(add)(arena, idx + wp.static(3 * cap), am, sm)
                        if wp.static(affine_flip == 1):
                            for c in range(3):
                                wp.static(add)(arena, idx + (4 + c) * wp.static(cap), old[c], sp)
                    if valid and not fits:
                        node = ((base[0] + ii) * n_grid + base[1] + jj) * n_grid + base[2] + kk
                        wp.atomic_add(grid_mv, node, a)
                        wp.atomic_add(grid_m, node, am)
                        if wp.static(affine_flip == 1):
                            wp.atomic_add(grid_mv_old, node, old)
        if any_valid and not fits and lane == 0:
            wp.atomic_add(spilled, 0, 1)
        if wp.static(not tiles):
            block_sync()
        if fits:
            for idx in range(lane, e[0] * e[1] * e[2], threads):
                s4 = wp.vec4(0.0)
                s3 = wp.vec3(0.0)
                if wp.static(tiles):
                    s4 = a_mv[idx]
                    if wp.static(affine_flip == 1):
                        s3 = a_old[idx]
                else:
                    for c in range(3):
                        s4[c] = wp.static(get)(arena, idx + c * wp.static(cap), sp)
                    s4[3] = wp.static(get)(arena, idx + wp.static(3 * cap), sm)
                    if wp.static(affine_flip == 1):
                        for c in range(3):
                            s3[c] = wp.static(get)(arena, idx + (4 + c) * wp.static(cap), sp)
                if s4[3] != 0.0:
                    node = ((o[0] + idx // (e[1] * e[2])) * n_grid + o[1] + (idx // e[2]) % e[1]) * n_grid \
                        + o[2] + idx % e[2]
                    wp.atomic_add(grid_mv, node, wp.vec3(s4[0], s4[1], s4[2]))
                    wp.atomic_add(grid_m, node, s4[3])
                    if wp.static(affine_flip == 1):
                        wp.atomic_add(grid_mv_old, node, s3)

    return wp.kernel(g2p2g_arena, name=f"g2p2g_{arena}_{cap}_{regs}_{affine_flip}", cuda_max_registers=regs or None,
                     module="unique", enable_backward=False)


def build(args):
    """The model, its particles' initial positions and a label."""
    from knockgs_core.sim import Probe, SimParams, build_model

    if args.object == "block":
        from sim_bench import block

        X = block(args.particles_count, args.n_grid)
        params = SimParams(n_grid=args.n_grid, dt=1e-4, transfer=args.transfer)
        X = X[block_order(X, params.dx, args.tile, interleave=args.interleave)]
        model = build_model(X, E=1e4, nu=0.3, rho=2000.0, params=params,
                            probe=Probe("standard_x", (-0.18, 0.0, 0.0)), device=args.device)
        return model, X
    from _object_model import object_particles, probe_a_model

    from knockgs_core.contract import load_contract
    from knockgs_core.rollout import _permuted

    contract = load_contract(args.object, args.profile)
    ps = object_particles(contract, args.particles)
    dx, g = contract.sim.grid_lim / contract.sim.n_grid, int(ps.n_gs)
    X = np.asarray(ps.positions)  # the Gaussian-associated rows stay first, as in a rollout
    il = args.interleave
    ps = _permuted(ps, np.concatenate([block_order(X[:g], dx, args.tile, interleave=il),
                                       g + block_order(X[g:], dx, args.tile, interleave=il)]))
    return probe_a_model(contract, ps, args.device), ps.positions


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="block", help="block, or a contract's object (pillow, ficus, vasedeck)")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--particles", help="the object's particle file (cached)")
    ap.add_argument("--particles-count", type=int, default=681472, help="the block's particles")
    ap.add_argument("--n-grid", type=int, default=100, help="the block's grid")
    ap.add_argument("--transfer", default="affine_flip", choices=["affine_flip", "apic"])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--tile", type=int, default=4, help="grid block side [cells] of the particles' order")
    ap.add_argument("--interleave", type=int, default=0,
                    help="cells a group: within a grid block's groups of cells, the cells' first particles, then "
                         "their second, ... (block_order; 0: cell order)")
    ap.add_argument("--warm", type=int, default=40)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--block", type=int, nargs="+", default=[256], help="threads (particles) a CUDA block")
    ap.add_argument("--cap", type=int, nargs="+", default=[1024], help="arena nodes")
    ap.add_argument("--regs", type=int, nargs="+", default=[0], help="register caps (0: none)")
    ap.add_argument("--arena", nargs="+", choices=["tiles", "atomics", "fixed"], default=["tiles"],
                    help="how a block sums into its arena: Warp's tile_scatter_add (a block barrier a scatter), "
                         "float shared atomics through native snippets (three barriers a block), or int64 shared "
                         "atomics of fixed-point units (the reproducible P2G's)")
    ap.add_argument("--rotate", type=int, nargs="+", choices=[0, 1], default=[0],
                    help="1: each particle visits its stencil nodes from node p mod 27 on (shared-atomics arenas)")
    ap.add_argument("--merge-zero", action="store_true",
                    help="zero the other grids in the grid update's pass (one launch a substep less)")
    ap.add_argument("--box", nargs="+", choices=["atomics", "warp"], default=["atomics"],
                    help="the block's box of base cells by shared atomics of every lane, or reduced in each warp first")
    args = ap.parse_args()
    from knockgs_core.sim import MPMSolver, make_state

    wp.init()
    dev = args.device
    cuda = wp.get_device(dev).is_cuda
    model, X = build(args)
    p = model.params
    n = model.particle_count
    state = make_state(model, X)
    solver = MPMSolver(model, p2g="cells" if cuda else "scatter", graph=False, fuse=False)
    solver.check(state)
    for _ in range(args.warm):
        solver.step(state)
        if state.step % p.guard_every == 0:
            solver.check(state)
    solver.check(state)
    wp.synchronize_device(dev)
    print(f"{args.object}: {n} particles, box {solver._lo}..{solver._hi}, step {state.step}, "
          f"probe steps {model.probe_first}..{model.probe_first + model.probe_steps}, tile {args.tile}, "
          f"interleaved {args.interleave}", flush=True)
    pipe = FusedPipeline(model, state, solver)
    pipe.merge_zero = args.merge_zero
    b = pipe.base
    print(f"baseline: p2g {b.p2g}, sums {b.cell_sums}, fuse {b.fuse}, graph {b.graph}", flush=True)
    spilled = wp.zeros(1, dtype=wp.int32, device=dev)

    def launcher(kernel, bd):
        def fused(S, D):
            wp.launch_tiled(kernel, dim=-(-n // bd) if cuda else n, block_dim=bd,
                            inputs=[S["grid_mv"].flatten(), solver._inv_dx, p.dt, pipe.zero_mask, wp.vec3(0.0), 0, pipe.lo,
                                    pipe.hi, state.particle_x0, p.flip_weight, S["grid_mv_old"].flatten(),
                                    solver._g2p_lines, model.particle_mass, model.particle_vol, model.particle_mu,
                                    model.particle_lam, model.probe_mask, wp.vec3(*model.probe_force), 0,
                                    solver.polar_iters, solver.polar_step, solver._polar_rational, solver.retardation,
                                    p.n_grid, n],
                            outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F,
                                     state.particle_rot, pipe.overrun, spilled, D["grid_mv"].flatten(),
                                     D["grid_m"].flatten(), D["grid_mv_old"].flatten()], device=dev)
        return fused

    units = _FixedScratch(model)  # the solver's fixed-point units
    scales = (units.scale_m, units.scale_p)
    variants = [(ar, rot, bx) for ar in args.arena for rot in args.rotate for bx in args.box
                if ar != "tiles" or (rot == 0 and bx == "atomics")]
    made = {(v, cap, regs): make_kernel(cap, regs, pipe.flip, v[0], scales, rotate=v[1], warp_box=int(v[2] == "warp"))
            for v in variants for cap in args.cap for regs in args.regs}
    kernels = {(v, bd, cap, regs): made[v, cap, regs] for v in variants for bd in args.block for cap in args.cap
               for regs in args.regs}
    res = {}
    u_arena = {}

    def name(key):
        (ar, rot, bx), bd, cap, regs = key
        return f"{ar}{' rotated' if rot else ''}{' warp box' if bx == 'warp' else ''} block {bd} cap {cap} regs {regs}"
    for r in range(args.repeats):
        tb = pipe.time_base(args.steps)
        res.setdefault("base", []).append(tb)
        u_base = state.particle_u.numpy().astype(np.float64)
        for key, kernel in kernels.items():
            spilled.zero_()
            res.setdefault(key, []).append(pipe.time_fused(launcher(kernel, key[1]), args.steps))
            u_arena[key] = state.particle_u.numpy().astype(np.float64)
        runs = ", ".join(f"{name(k)}: {1e3 * v[-1]:.4f}" for k, v in res.items() if k != "base")
        print(f"repeat {r}: base {1e3 * tb:.4f} ms, {runs}", flush=True)
    rms = float(np.sqrt((u_base ** 2).sum(1).mean()))
    print(f"u RMS {rms:.6e} m; overrun {int(pipe.overrun.numpy()[0])}; blocks spilled in the last run (over its "
          f"substeps) {int(spilled.numpy()[0])}")
    for key, u in u_arena.items():
        d = float(np.sqrt(((u_base - u) ** 2).sum(1).mean()))
        print(f"{name(key)}: base vs arena RMS difference {d:.3e} m ({d / rms:.2e} of the RMS)")
    for k, v in res.items():
        print(f"{k if k == 'base' else name(k)}: median {1e3 * float(np.median(v)):.4f} ms a substep")


if __name__ == "__main__":
    main()
