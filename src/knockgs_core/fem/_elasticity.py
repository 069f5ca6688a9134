"""Small-strain linear elasticity on tetrahedra: stiffness, mass, loads, supports, interpolation.

The weak form is the textbook one (Hughes, *The Finite Element Method*, ch. 2 and 7):
``K = int eps(v) : C eps(u) dV`` with the isotropic ``C eps = 2 mu eps + lambda tr(eps) I``,
``M = int rho u . v dV`` and a body force density ``b`` [N/m^3] giving ``f = int b . v dV``.
Assembly is scikit-fem's (vector Lagrange elements, Gauss quadrature exact for the mass).

The MPM's fixed-corotated energy ``mu |F - R|^2 + lambda/2 (J - 1)^2`` has the same second
variation at ``F = I`` as this linear energy, ``mu |eps|^2 + lambda/2 tr(eps)^2``: at the
strains of the probes (~1e-3) the two differ by terms of relative size ~1e-3 (geometric
nonlinearity), below every discretization error compared here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal, Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
from skfem.helpers import ddot, dot, sym_grad, trace

from ..errors import InputError
from ._mesh import Region

__all__ = ["MASS_KINDS", "ElasticSystem", "assemble_elasticity", "body_force_load", "support_dofs", "static_solve",
           "natural_frequencies", "find_elements", "interpolation_matrix", "interpolate", "lame"]

MASS_KINDS = ("consistent", "lumped")


def lame(E: float, nu: float) -> tuple[float, float]:
    """(mu, lambda) [Pa] of Young's modulus ``E`` [Pa] and Poisson ratio ``nu`` [-]."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@dataclass
class ElasticSystem:
    """An assembled elastic body: ``K`` stiffness [N/m] and ``M`` mass [kg], both sparse CSR,
    shape (n_dofs, n_dofs); ``basis`` the scikit-fem vector basis (DOF numbering and
    locations, ``basis.doflocs`` shape (3, n_dofs) [m]). ``mass`` says whether ``M`` is the
    consistent mass or its row-sum lumped diagonal. ``E`` [Pa], ``nu`` [-], ``rho``
    [kg/m^3]: the material's (uniform unless a field of :func:`assemble_elasticity` scales
    them)."""

    mesh: skfem.MeshTet
    basis: skfem.Basis
    K: sp.csr_matrix
    M: sp.csr_matrix
    E: float
    nu: float
    rho: float
    degree: int
    mass: str
    _probes: dict = field(default_factory=dict, repr=False)

    @property
    def n_dofs(self) -> int:
        return int(self.basis.N)

    @property
    def volume(self) -> float:
        """Volume of the meshed body [m^3] (its mass over ``rho``: a mass field's share)."""
        return float(self.M.sum() / (3.0 * self.rho))


def assemble_elasticity(mesh: skfem.MeshTet, *, E: float, nu: float, rho: float, degree: int = 1,
                        mass: Literal["consistent", "lumped"] = "consistent",
                        stiffness_field: Callable[[np.ndarray], np.ndarray] | None = None,
                        mass_field: Callable[[np.ndarray], np.ndarray] | None = None) -> ElasticSystem:
    """Assemble stiffness and mass of an isotropic body on ``mesh``.

    ``degree`` 1: linear tetrahedra (P1, the reference); 2: quadratic (P2, a cross-check of
    the P1 mesh convergence). ``mass``: ``"consistent"`` (the Galerkin mass) or
    ``"lumped"`` (row sums on the diagonal; P1 only, where they are positive).
    ``stiffness_field``: the modulus varies in space, ``E(x) = E * stiffness_field(x)``, a
    positive factor of the coordinates ``x`` [3, ...] m (evaluated at the quadrature points);
    None: a uniform body. ``mass_field``: the density varies likewise, ``rho(x) = rho *
    mass_field(x)`` (a body whose cells are partly filled: :mod:`._world`); None: uniform.
    ``nu`` stays uniform."""
    if mass not in MASS_KINDS:
        raise ValueError(f"mass must be one of {', '.join(MASS_KINDS)}, got {mass!r}")
    if degree not in (1, 2):
        raise InputError("fem.assemble_elasticity", "degree", f"must be 1 (P1) or 2 (P2), got {degree!r}")
    if mass == "lumped" and degree != 1:
        raise InputError("fem.assemble_elasticity", "mass",
                         "row-sum lumping is defined for P1 only (P2's vertex sums are not positive)")
    if not (E > 0 and rho > 0 and -1.0 < nu < 0.5):
        raise InputError("fem.assemble_elasticity", "E/nu/rho", f"need E > 0, rho > 0, -1 < nu < 0.5, got {E!r}, {nu!r}, {rho!r}")
    elem = skfem.ElementVector(skfem.ElementTetP1() if degree == 1 else skfem.ElementTetP2())
    basis = skfem.Basis(mesh, elem, intorder=2 * degree)
    mu, lam = lame(E, nu)

    @skfem.BilinearForm
    def stiffness(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        f = 1.0 if stiffness_field is None else stiffness_field(np.asarray(w.x))
        return f * (2.0 * mu * ddot(eu, ev) + lam * trace(eu) * trace(ev))

    @skfem.BilinearForm
    def inertia(u, v, w):
        f = 1.0 if mass_field is None else mass_field(np.asarray(w.x))
        return f * rho * dot(u, v)

    for name, fn in (("stiffness_field", stiffness_field), ("mass_field", mass_field)):
        if fn is not None:
            f = np.asarray(fn(np.asarray(basis.global_coordinates())), dtype=np.float64)
            if not (np.all(np.isfinite(f)) and np.all(f > 0)):
                raise InputError("fem.assemble_elasticity", name, "must be a finite positive factor everywhere")
    K = stiffness.assemble(basis).tocsr()
    M = inertia.assemble(basis).tocsr()
    if mass == "lumped":
        M = sp.diags(np.asarray(M.sum(axis=1)).ravel()).tocsr()
    return ElasticSystem(mesh=mesh, basis=basis, K=K, M=M, E=float(E), nu=float(nu), rho=float(rho),
                         degree=int(degree), mass=mass)


def body_force_load(system: ElasticSystem, density: Sequence[float], region: Region | None = None) -> np.ndarray:
    """Load vector [N] of a uniform body force density ``density`` [N/m^3] (length 3) over
    the body, or over the part of it inside ``region`` (selected at the quadrature points:
    exact when the region's faces lie on element faces). Shape (n_dofs,); the sum of its
    entries of one component is the total force along that axis."""
    b = np.asarray(density, dtype=np.float64)
    if b.shape != (3,) or not np.all(np.isfinite(b)):
        raise InputError("fem.body_force_load", "density", f"need a finite length-3 force density [N/m^3], got {density!r}")

    @skfem.LinearForm
    def load(v, w):
        val = b[0] * v[0] + b[1] * v[1] + b[2] * v[2]
        if region is None:
            return val
        x = w.x
        inside = np.ones(x.shape[1:], dtype=bool)
        for k in range(3):
            inside &= (x[k] >= region.lo[k] - 1e-12) & (x[k] <= region.hi[k] + 1e-12)
        return val * inside

    return load.assemble(system.basis)


def _dof_components(system: ElasticSystem) -> np.ndarray:
    """The displacement component (0 x, 1 y, 2 z) of every DOF, shape (n_dofs,)."""
    comp = np.zeros(system.n_dofs, dtype=np.int64)
    for dofs in (system.basis.nodal_dofs, system.basis.edge_dofs):
        if dofs.size:
            for k in range(3):
                comp[dofs[k]] = k
    return comp


def support_dofs(system: ElasticSystem, region: Region, *, tol: float = 1e-9,
                 components: Sequence[int] = (0, 1, 2)) -> np.ndarray:
    """Indices of the DOFs of the nodes inside ``region`` (widened by ``tol`` [m]): a support
    that holds them fixed. ``components``: the displacement components held (0 x, 1 y, 2 z),
    all three by default (a clamp); e.g. ``(2,)`` holds only the z motion (a roller)."""
    comp = np.asarray(components, dtype=np.int64).ravel()
    if comp.size == 0 or np.any((comp < 0) | (comp > 2)):
        raise InputError("fem.support_dofs", "components", f"need some of 0, 1, 2, got {components!r}")
    inside = region.contains(system.basis.doflocs.T, tol=tol)
    return np.flatnonzero(inside & np.isin(_dof_components(system), comp))


def _free(system: ElasticSystem, fixed) -> np.ndarray:
    mask = np.ones(system.n_dofs, dtype=bool)
    mask[np.asarray(fixed, dtype=np.int64)] = False
    return np.flatnonzero(mask)


def static_solve(system: ElasticSystem, load: np.ndarray, fixed) -> np.ndarray:
    """Equilibrium displacement [m] under ``load`` [N] (n_dofs,) with the DOFs ``fixed`` held
    at zero: solves ``K_ff u_f = f_f``. Shape (n_dofs,)."""
    free = _free(system, fixed)
    u = np.zeros(system.n_dofs)
    K = system.K[free][:, free].tocsc()
    u[free] = spla.splu(K, permc_spec="MMD_AT_PLUS_A").solve(np.asarray(load, dtype=np.float64)[free])
    return u


def natural_frequencies(system: ElasticSystem, fixed, *, n_modes: int) -> np.ndarray:
    """The ``n_modes`` lowest natural frequencies [Hz] of ``system`` with the DOFs ``fixed``
    (indices into its n_dofs) held at zero, ascending, shape (n_modes,).

    Solves the generalized eigenproblem ``K_ff phi = omega^2 M_ff phi`` on the free DOFs with
    the system's own mass (consistent, or lumped if it was assembled so) by Lanczos iterations
    in shift-invert mode (:func:`scipy.sparse.linalg.eigsh`) about a small negative shift, so
    that ``K_ff - sigma M_ff`` is positive definite also for a body with rigid motions left
    free; those come out at 0 Hz up to round-off (about 1e-6 of the lowest elastic frequency;
    round-off below zero is clipped). Returns ``f = omega / (2 pi)``."""
    free = _free(system, fixed)
    if not (isinstance(n_modes, (int, np.integer)) and 1 <= n_modes < len(free)):
        raise InputError("fem.natural_frequencies", "n_modes",
                         f"need an integer in [1, {len(free) - 1}] (free DOFs - 1), got {n_modes!r}")
    K = system.K[free][:, free].tocsc()
    M = system.M[free][:, free].tocsc()
    # sigma < 0 keeps K - sigma M positive definite with rigid motions free; 1e-8 of the largest
    # diagonal K/M ratio (about the mesh's highest omega^2) is small against the lowest elastic
    # omega^2 (a tenth of it for FV32). The shift moves no eigenvalue, only the Lanczos rate.
    sigma = -1e-8 * float(np.max(K.diagonal() / M.diagonal()))
    omega2 = spla.eigsh(K, k=int(n_modes), M=M, sigma=sigma, which="LM", return_eigenvectors=False)
    return np.sqrt(np.clip(np.sort(omega2), 0.0, None)) / (2.0 * np.pi)


def find_elements(mesh: skfem.MeshTet, points: np.ndarray, *, tol: float = 1e-10) -> np.ndarray:
    """Index of a tetrahedron of ``mesh`` containing each of ``points`` [m] (n, 3), or -1.

    Elements are binned by their bounding boxes on a uniform grid of buckets (the median
    element extent per axis); a point's candidates are its bucket's elements, tested by their
    barycentric coordinates (all >= -tol). Memory stays linear in points and elements, also
    for elongated elements (a thick layer beside a fine one)."""
    x = np.asarray(points, dtype=np.float64)
    p, t = mesh.p.T, mesh.t.T
    corners = p[t]                                            # (n_el, 4, 3)
    lo_el, hi_el = corners.min(axis=1), corners.max(axis=1)
    origin = p.min(axis=0)
    size = np.maximum(np.median(hi_el - lo_el, axis=0), 1e-12)
    n_b = np.maximum(np.ceil((p.max(axis=0) - origin) / size).astype(np.int64), 1)
    i0 = np.clip(np.floor((lo_el - origin) / size - 1e-9).astype(np.int64), 0, n_b - 1)
    i1 = np.clip(np.floor((hi_el - origin) / size + 1e-9).astype(np.int64), 0, n_b - 1)
    span = i1 - i0 + 1
    buckets, elems = [], []
    for off in np.ndindex(*span.max(axis=0)):
        sel = np.all(np.asarray(off) < span, axis=1)
        idx = i0[sel] + np.asarray(off)
        buckets.append((idx[:, 0] * n_b[1] + idx[:, 1]) * n_b[2] + idx[:, 2])
        elems.append(np.flatnonzero(sel))
    buckets, elems = np.concatenate(buckets), np.concatenate(elems)
    order = np.argsort(buckets, kind="stable")
    buckets, elems = buckets[order], elems[order]
    ip = np.clip(np.floor((x - origin) / size).astype(np.int64), 0, n_b - 1)
    key = (ip[:, 0] * n_b[1] + ip[:, 1]) * n_b[2] + ip[:, 2]
    start, stop = np.searchsorted(buckets, key, "left"), np.searchsorted(buckets, key, "right")
    count = stop - start
    point = np.repeat(np.arange(len(x)), count)
    cand = elems[np.repeat(start - np.cumsum(count) + count, count) + np.arange(count.sum())]
    v0 = corners[cand, 0]
    T = np.stack([corners[cand, 1] - v0, corners[cand, 2] - v0, corners[cand, 3] - v0], axis=2)
    lam = np.linalg.solve(T, (x[point] - v0)[:, :, None])[:, :, 0]
    ok = (lam >= -tol).all(axis=1) & (lam.sum(axis=1) <= 1.0 + tol)
    found = np.full(len(x), -1, dtype=np.int64)
    found[point[ok][::-1]] = cand[ok][::-1]                 # the first containing candidate wins
    return found


def interpolation_matrix(system: ElasticSystem, points: np.ndarray) -> sp.csr_matrix:
    """Sparse matrix ``P`` (3 n_points, n_dofs) with ``P @ u`` the displacement at ``points``
    [m] (n_points, 3), component-major (all x, then y, then z), from the element basis
    (as scikit-fem's ``Basis.probes``, with the point location of :func:`find_elements`,
    whose memory stays linear in the number of points). Every point must lie in the meshed body."""
    x = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] == 0 or not np.all(np.isfinite(x)):
        raise InputError("fem.interpolation_matrix", "points", f"need finite points of shape (n, 3), got {x.shape}")
    cells = find_elements(system.mesh, x)
    if np.any(cells < 0):
        bad = x[np.flatnonzero(cells < 0)[0]]
        raise InputError("fem.interpolation_matrix", "points",
                         f"{int(np.sum(cells < 0))} points lie in no element, e.g. {bad.tolist()}")
    basis = system.basis
    ref = basis.mapping.invF(x.T[:, :, None], tind=cells)
    phis = np.array([basis.elem.gbasis(basis.mapping, ref, k, tind=cells)[0] for k in range(basis.Nbfun)])  # (Nbfun, 3, n, 1)
    n = len(x)
    rows = np.tile(np.arange(3 * n), basis.Nbfun)
    cols = basis.element_dofs[:, np.tile(cells, 3)].ravel()
    return sp.coo_matrix((phis.ravel(), (rows, cols)), shape=(3 * n, basis.N)).tocsr()


def interpolate(system: ElasticSystem, U: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Displacements ``U`` [m] (frames, n_dofs) or (n_dofs,) evaluated at ``points`` [m]
    (n_points, 3): shape (frames, n_points, 3) or (n_points, 3)."""
    P = interpolation_matrix(system, points)
    n = len(points)
    U = np.asarray(U, dtype=np.float64)
    if U.ndim == 1:
        return (P @ U).reshape(3, n).T
    return (P @ U.T).reshape(3, n, U.shape[0]).transpose(2, 1, 0)
