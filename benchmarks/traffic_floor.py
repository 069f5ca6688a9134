"""The memory floor of our GPU substep's particle kernels: their particle arrays streamed with no
grid and next to no arithmetic.

``stream_g2p_prepare`` reads and writes what ``_kernels.g2p_prepare`` reads and writes per
particle (the state: x0, u, v, C, F in float64, the rotation, mass, volume, mu, lambda, the two
masks; the P2G terms: fx, mv, affine, mC, the key), each value feeding an output so the loads
stay; ``stream_terms`` reads what ``p2g_windows`` reads per sorted position (the order, the
key, fx, mv, affine, mC) and writes one float. A device-to-device copy of the F array gives the
device's streaming bandwidth. Each is launched ``--launches`` times, ``--repeats`` times; the
median is reported, in ms a launch and in GB/s of the bytes named above. The particles are in
their own order (``order`` the identity): the best case for the terms' reads.

    python3 benchmarks/traffic_floor.py --device cuda:0 --particles 681472 695881
    python3 benchmarks/traffic_floor.py --device cpu --particles 20000 --launches 5
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

#: bytes a particle: reads and writes of stream_g2p_prepare, reads and the write of stream_terms
PREPARE_BYTES = (12 + 12 + 12 + 36 + 72 + 16 + 4 * 4 + 2 * 4) + (12 + 12 + 36 + 72 + 16 + 12 + 16 + 36 + 36 + 4)
TERMS_BYTES = (4 + 4 + 12 + 16 + 36 + 36) + 4


@wp.kernel
def stream_g2p_prepare(
    dt: float,
    x0: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    trans_mask: wp.array(dtype=wp.int32),
    probe_mask: wp.array(dtype=wp.int32),
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33d),
    rot: wp.array(dtype=wp.quat),
    fx: wp.array(dtype=wp.vec3),
    mv: wp.array(dtype=wp.vec4),
    affine: wp.array(dtype=wp.mat33),
    mC: wp.array(dtype=wp.mat33),
    keys: wp.array(dtype=wp.int32),
):
    """Read particle ``p``'s state, write its state and P2G terms (trivial arithmetic)."""
    p = wp.tid()
    m = mass[p]
    up = u[p] + dt * v[p]
    vp = v[p] * (1.0 + float(trans_mask[p] + probe_mask[p]))
    Cp = C[p]
    Fp = F[p] * wp.float64(1.0 + dt * vol[p])
    u[p] = up
    v[p] = vp
    C[p] = Cp * (1.0 - dt)
    F[p] = Fp
    rot[p] = rot[p] * (1.0 + dt * lam[p])
    fx[p] = x0[p] + up
    mv[p] = wp.vec4(vp[0], vp[1], vp[2], m)
    affine[p] = Cp * mu[p]
    mC[p] = Cp * m
    keys[p] = int(Fp[0, 0])


@wp.kernel
def stream_g2p_prepare_soa(
    dt: float,
    x0: wp.array2d(dtype=float),
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    trans_mask: wp.array(dtype=wp.int32),
    probe_mask: wp.array(dtype=wp.int32),
    u: wp.array2d(dtype=float),
    v: wp.array2d(dtype=float),
    C: wp.array2d(dtype=float),
    F: wp.array2d(dtype=wp.float64),
    rot: wp.array2d(dtype=float),
    fx: wp.array2d(dtype=float),
    mv: wp.array2d(dtype=float),
    affine: wp.array2d(dtype=float),
    mC: wp.array2d(dtype=float),
    keys: wp.array(dtype=wp.int32),
):
    """:func:`stream_g2p_prepare` with every vector and matrix stored component by component
    (shape (components, N): consecutive particles' components side by side)."""
    p = wp.tid()
    m = mass[p]
    s = 1.0 + float(trans_mask[p] + probe_mask[p])
    for k in range(3):
        up = u[k, p] + dt * v[k, p]
        u[k, p] = up
        fx[k, p] = x0[k, p] + up
        vk = v[k, p] * s
        v[k, p] = vk
        mv[k, p] = vk
    mv[3, p] = m
    g = wp.float64(1.0 + dt * vol[p])
    f00 = F[0, p] * g
    for k in range(9):
        c = C[k, p]
        C[k, p] = c * (1.0 - dt)
        F[k, p] = F[k, p] * g
        affine[k, p] = c * mu[p]
        mC[k, p] = c * m
    for k in range(4):
        rot[k, p] = rot[k, p] * (1.0 + dt * lam[p])
    keys[p] = int(f00)


@wp.kernel
def stream_g2p_prepare_mixed(
    dt: float,
    x0: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    trans_mask: wp.array(dtype=wp.int32),
    probe_mask: wp.array(dtype=wp.int32),
    u: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array2d(dtype=float),
    F: wp.array2d(dtype=wp.float64),
    rot: wp.array(dtype=wp.quat),
    fx: wp.array(dtype=wp.vec3),
    mv: wp.array(dtype=wp.vec4),
    affine: wp.array2d(dtype=float),
    mC: wp.array2d(dtype=float),
    keys: wp.array(dtype=wp.int32),
):
    """:func:`stream_g2p_prepare` with the matrices (C, F, affine, mC) stored component by
    component and the vectors as they are."""
    p = wp.tid()
    m = mass[p]
    up = u[p] + dt * v[p]
    vp = v[p] * (1.0 + float(trans_mask[p] + probe_mask[p]))
    u[p] = up
    v[p] = vp
    rot[p] = rot[p] * (1.0 + dt * lam[p])
    fx[p] = x0[p] + up
    mv[p] = wp.vec4(vp[0], vp[1], vp[2], m)
    g = wp.float64(1.0 + dt * vol[p])
    f00 = F[0, p] * g
    for k in range(9):
        F[k, p] = F[k, p] * g
        c = C[k, p]
        C[k, p] = c * (1.0 - dt)
        affine[k, p] = c * mu[p]
        mC[k, p] = c * m
    keys[p] = int(f00)


@wp.kernel
def stream_terms(
    order: wp.array(dtype=wp.int32),
    keys: wp.array(dtype=wp.int32),
    fx: wp.array(dtype=wp.vec3),
    mv: wp.array(dtype=wp.vec4),
    affine: wp.array(dtype=wp.mat33),
    mC: wp.array(dtype=wp.mat33),
    out: wp.array(dtype=float),
):
    """Read sorted position ``s``'s terms through the order, write one float."""
    s = wp.tid()
    p = order[s]
    f = fx[p]
    q = mv[p]
    out[s] = float(keys[p]) + f[0] + q[3] + wp.trace(affine[p]) + wp.trace(mC[p])


def timed(fn, launches: int, repeats: int, device: str) -> float:
    """Median seconds a launch."""
    fn()
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(launches):
            fn()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t0) / launches)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--particles", type=int, nargs="+", default=[681472])
    ap.add_argument("--launches", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    dev = args.device
    rng = np.random.default_rng(0)
    print(f"# device {wp.get_device(dev).name if dev != 'cpu' else 'cpu'} ({dev}), Warp {wp.__version__}")
    print("| particles | kernel | B a particle | ms a launch | GB/s |")
    print("|---:|---|---:|---:|---:|")
    for n in args.particles:
        def arr(dtype, width, scale=1.0):
            shape = (n,) if width == 1 else (n, width)
            return wp.array((scale * rng.random(shape)).astype(np.float64 if dtype == wp.mat33d else np.float32),
                            dtype=dtype, device=dev)

        def ints():
            return wp.zeros(n, dtype=wp.int32, device=dev)

        x0, u, v = arr(wp.vec3, 3), arr(wp.vec3, 3, 1e-3), arr(wp.vec3, 3, 1e-3)
        C, F = arr(wp.mat33, 9, 1e-3), wp.array(np.tile(np.eye(3), (n, 1, 1)), dtype=wp.mat33d, device=dev)
        rot = wp.array(np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)).astype(np.float32), dtype=wp.quat, device=dev)
        mass, vol, mu, lam = (arr(float, 1) for _ in range(4))
        trans_mask, probe_mask, keys = ints(), ints(), ints()
        fx, mv = arr(wp.vec3, 3), arr(wp.vec4, 4)
        affine, mC = arr(wp.mat33, 9), arr(wp.mat33, 9)
        order = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=dev)
        out = wp.zeros(n, dtype=float, device=dev)
        F_copy = wp.empty_like(F)
        prepare = wp.launch(stream_g2p_prepare, dim=n, inputs=[1e-9, x0, mass, vol, mu, lam, trans_mask, probe_mask],
                            outputs=[u, v, C, F, rot, fx, mv, affine, mC, keys], device=dev, record_cmd=True)
        terms = wp.launch(stream_terms, dim=n, inputs=[order, keys, fx, mv, affine, mC], outputs=[out], device=dev,
                          record_cmd=True)
        pitch = -(-n // 32) * 32  # rows start 128-byte aligned

        def soa(width, dtype=float, scale=1.0):
            """A (width, pitch) array: particle p's component k at [k, p]."""
            return wp.array((scale * rng.random((width, pitch))).astype(np.float64 if dtype == wp.float64 else np.float32),
                            dtype=dtype, device=dev)

        prepare_soa = wp.launch(stream_g2p_prepare_soa, dim=n, inputs=[1e-9, soa(3), mass, vol, mu, lam, trans_mask,
                                                                        probe_mask],
                                outputs=[soa(3, scale=1e-3), soa(3, scale=1e-3), soa(9, scale=1e-3), soa(9, wp.float64),
                                         soa(4), soa(3), soa(4), soa(9), soa(9), ints()], device=dev, record_cmd=True)
        prepare_mixed = wp.launch(stream_g2p_prepare_mixed, dim=n, inputs=[1e-9, x0, mass, vol, mu, lam, trans_mask,
                                                                            probe_mask],
                                  outputs=[u, v, soa(9, scale=1e-3), soa(9, wp.float64), rot, fx, mv, soa(9), soa(9), keys],
                                  device=dev, record_cmd=True)
        rows = [
            ("stream_g2p_prepare", PREPARE_BYTES, prepare.launch),
            ("stream_g2p_prepare_soa (components apart)", PREPARE_BYTES, prepare_soa.launch),
            ("stream_g2p_prepare_mixed (matrices apart, vectors not)", PREPARE_BYTES, prepare_mixed.launch),
            ("stream_terms", TERMS_BYTES, terms.launch),
            ("copy of F (read + write)", 2 * 72, lambda: wp.copy(F_copy, F)),
        ]
        for name, nbytes, fn in rows:
            sec = timed(fn, args.launches, args.repeats, dev)
            print(f"| {n:,} | {name} | {nbytes} | {1e3 * sec:.4f} | {nbytes * n / sec / 1e9:.0f} |", flush=True)
        if not np.isfinite(u.numpy()).all():
            raise SystemExit("non-finite state")


if __name__ == "__main__":
    main()
