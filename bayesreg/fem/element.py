"""Linear-elastic finite elements on linear tetrahedra (paper Eqs. 2-7).

Conventions (used throughout :mod:`bayesreg`):

* ``nodes``: ``(N, 3)`` float, world coordinates in mm.
* ``tets``: ``(M, 4)`` int, positively oriented (``det[x1-x0, x2-x0, x3-x0] > 0``).
* displacements ``u``: ``(N, 3)`` mm; flattened DOF order is node-major, ``3*i + axis``.
* ``lam``, ``mu``: Lamé parameters per element, ``(M,)`` (a scalar broadcasts).  Their unit
  is arbitrary (only ratios matter for the FE solve, paper Sec. 3.3); energies are in
  ``[lam] * mm^3``.

The NumPy/SciPy functions here are the reference implementation (element matrices, the
assembly of ``K``, the strain energy); the JAX functions :func:`strain_energy_density` and
:func:`element_strain_energy` give ``E_r`` inside the log-density.  The matrix-free form of
``K`` used by the solver is :class:`bayesreg.fem.stiffness.ElasticOperator`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg._checks import as_index_array

__all__ = [
    "shape_gradients",
    "element_stiffness",
    "element_stiffness_voigt",
    "stiffness_matrix",
    "node_dofs",
    "InteriorSolver",
    "interior_solver",
    "strain_energy",
    "strain_energy_density",
    "element_strain_energy",
    "unit_element_stiffness",
    "check_mesh",
]

# d N_a / d xi for the reference tetrahedron, N = (1 - xi - eta - zeta, xi, eta, zeta).
_DN_DXI = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def check_mesh(nodes, tets):
    """``(nodes float64 (N, 3), tets int64 (M, 4))``, validated (host arrays only).

    Raises ``ValueError`` on a wrong shape, non-finite node coordinates, ``tets`` neither
    integer nor integral floats, or node indices outside ``[0, N)``."""
    try:
        nodes = np.asarray(nodes, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"nodes must be a (N, 3) array of floats, got {np.asarray(nodes).dtype}") from None
    tets = np.asarray(tets)
    if nodes.ndim != 2 or nodes.shape[1] != 3:
        raise ValueError(f"nodes must have shape (N, 3), got {nodes.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (M, 4), got {tets.shape}")
    if not np.all(np.isfinite(nodes)):
        bad = np.flatnonzero(~np.all(np.isfinite(nodes), axis=1))
        raise ValueError(f"nodes must be finite, got NaN or inf at node(s) {bad[:10].tolist()}")
    tets = as_index_array(tets, "tets")
    if tets.size and (tets.min() < 0 or tets.max() >= len(nodes)):
        raise ValueError(f"tets reference node indices outside [0, {len(nodes)}), got values "
                         f"{tets.min()}..{tets.max()}")
    return nodes, tets


def _per_element(value, m, name):
    """``value`` as ``(m,)`` float64 (a scalar broadcasts); finite and ``>= 0`` (host arrays
    only: the JAX functions used by the log-density take any values)."""
    value = np.asarray(value, dtype=np.float64)
    if value.ndim == 0:
        value = np.full(m, float(value))
    elif value.shape != (m,):
        raise ValueError(f"{name} must be a scalar or have shape ({m},), got {value.shape}")
    if not np.all(np.isfinite(value) & (value >= 0)):
        bad = value[~(np.isfinite(value) & (value >= 0))]
        raise ValueError(f"{name} must be finite and >= 0, got {bad[0]} "
                         f"({len(bad)} of {m} values bad)")
    return value


def shape_gradients(nodes, tets):
    """Gradients of the linear shape functions and element volumes.

    Parameters
    ----------
    nodes : (N, 3) array_like
        Node coordinates, world mm.
    tets : (M, 4) array_like of int
        Element connectivity.

    Returns
    -------
    grads : (M, 4, 3) ndarray
        ``grads[e, a] = grad N_a`` on element ``e`` (1/mm).
    volumes : (M,) ndarray
        Signed volumes (mm^3); positive for positively oriented elements.

    Raises
    ------
    ValueError
        On malformed shapes, non-finite node coordinates, non-integer ``tets`` or node
        indices outside ``[0, N)``, or a degenerate (zero-volume) element.
    """
    nodes, tets = check_mesh(nodes, tets)
    x = nodes[tets]  # (M, 4, 3)
    jac = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=-1)
    det = np.linalg.det(jac)
    degenerate = np.abs(det) <= 1e-12 * np.max(np.abs(det), initial=1.0)
    if np.any(degenerate):
        raise ValueError(f"{int(np.sum(degenerate))} degenerate element(s), e.g. element "
                         f"{int(np.flatnonzero(degenerate)[0])}")
    inv = np.linalg.inv(jac)  # (M, 3, 3): rows d xi / d x
    grads = np.einsum("aj,mjk->mak", _DN_DXI, inv)
    return grads, det / 6.0


def element_stiffness(nodes, tets, lam, mu):
    """Element stiffness matrices ``K_e = V_e B_e^T C_e B_e`` (paper Eq. 6).

    Written in index form, ``K_e[3a+i, 3b+j] = V (lam g_ai g_bj + mu (g_aj g_bi +
    delta_ij g_a . g_b))`` with ``g_a = grad N_a``; identical to the Voigt form of Eqs. 4-6
    (see :func:`element_stiffness_voigt`).

    Parameters
    ----------
    nodes : (N, 3) array_like
    tets : (M, 4) array_like of int
    lam, mu : float or (M,) array_like
        Lamé parameters per element (finite, ``>= 0``).

    Returns
    -------
    (M, 12, 12) ndarray
        Local DOF order ``3*a + axis`` for local node ``a``.

    Raises
    ------
    ValueError
        As :func:`shape_gradients`, or ``lam``/``mu`` not a scalar or ``(M,)``, non-finite
        or negative.
    """
    klam, kmu = unit_element_stiffness(nodes, tets)
    m = klam.shape[0]
    lam = _per_element(lam, m, "lam")
    mu = _per_element(mu, m, "mu")
    return lam[:, None, None] * klam + mu[:, None, None] * kmu


def unit_element_stiffness(nodes, tets):
    """The parts of ``K_e`` multiplying ``lam`` and ``mu`` (``(M, 12, 12)`` each)."""
    g, vol = shape_gradients(nodes, tets)
    vol = np.abs(vol)
    m = g.shape[0]
    klam = np.einsum("m,mai,mbj->maibj", vol, g, g).reshape(m, 12, 12)
    gg = np.einsum("mak,mbk->mab", g, g)
    kmu = np.einsum("m,maj,mbi->maibj", vol, g, g) + np.einsum(
        "m,mab,ij->maibj", vol, gg, np.eye(3)
    )
    return klam, kmu.reshape(m, 12, 12)


def strain_displacement_matrix(grads):
    """The Voigt strain-displacement matrix ``B`` of paper Eq. 4 for linear tetrahedra.

    Parameters
    ----------
    grads : (M, 4, 3) array_like
        Shape-function gradients from :func:`shape_gradients`.

    Returns
    -------
    (M, 6, 12) ndarray
        Rows ``[e_xx, e_yy, e_zz, g_xy, g_xz, g_yz]`` (engineering shear strains).
    """
    g = np.asarray(grads)
    b = np.zeros((g.shape[0], 6, 12))
    for a in range(4):
        gx, gy, gz = g[:, a, 0], g[:, a, 1], g[:, a, 2]
        c = 3 * a
        b[:, 0, c] = gx
        b[:, 1, c + 1] = gy
        b[:, 2, c + 2] = gz
        b[:, 3, c], b[:, 3, c + 1] = gy, gx
        b[:, 4, c], b[:, 4, c + 2] = gz, gx
        b[:, 5, c + 1], b[:, 5, c + 2] = gz, gy
    return b


def material_matrix(lam, mu):
    """Isotropic material matrix ``C`` of paper Eq. 5, shape ``(6, 6)``."""
    c = np.zeros((6, 6))
    c[:3, :3] = lam
    c[[0, 1, 2], [0, 1, 2]] = lam + 2 * mu
    c[[3, 4, 5], [3, 4, 5]] = mu
    return c


def element_stiffness_voigt(nodes, tets, lam, mu):
    """``V_e B^T C B`` assembled literally from paper Eqs. 4-6 (a slow reference).

    Same signature, result and errors as :func:`element_stiffness`.
    """
    g, vol = shape_gradients(nodes, tets)
    b = strain_displacement_matrix(g)
    m = len(vol)
    lam = _per_element(lam, m, "lam")
    mu = _per_element(mu, m, "mu")
    c = np.stack([material_matrix(l_, m_) for l_, m_ in zip(lam, mu)])
    return np.abs(vol)[:, None, None] * np.einsum("mki,mkl,mlj->mij", b, c, b)


def _dof_index(tets):
    return (3 * np.asarray(tets)[:, :, None] + np.arange(3)).reshape(len(tets), 12)


def stiffness_matrix(nodes, tets, lam, mu):
    """Global stiffness matrix ``K`` (paper Eq. 7) as SciPy sparse CSR.

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    lam, mu : float or (M,) array_like
        Lamé parameters, per element or uniform (finite, ``>= 0``).

    Returns
    -------
    scipy.sparse.csr_array, shape (3N, 3N)
        Symmetric positive semi-definite; its null space holds the six rigid-body modes.

    Raises
    ------
    ValueError
        As :func:`element_stiffness`.
    """
    nodes, tets = check_mesh(nodes, tets)
    ke = element_stiffness(nodes, tets, lam, mu)
    dof = _dof_index(tets)
    rows = np.repeat(dof, 12, axis=1).ravel()
    cols = np.tile(dof, (1, 12)).ravel()
    n = 3 * len(nodes)
    return sp.csr_array(sp.coo_array((ke.ravel(), (rows, cols)), shape=(n, n)))


def node_dofs(nodes) -> np.ndarray:
    """The DOF indices ``3*i + axis`` ``(3 n,)`` of the nodes ``nodes`` ``(n,)``, node-major."""
    return (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()


class InteriorSolver(NamedTuple):
    """The Dirichlet split of a global stiffness ``K`` (:func:`interior_solver`).

    Attributes
    ----------
    lu : scipy.sparse.linalg.SuperLU
        Sparse LU of ``K_ii``.
    k_ib : scipy.sparse matrix, shape (3 n_i, 3 n_b)
    boundary_dofs, interior_dofs : (3 n_b,), (3 n_i,) int arrays
        :func:`node_dofs` of the boundary and interior nodes, in the order given.
    """

    lu: object
    k_ib: object
    boundary_dofs: np.ndarray
    interior_dofs: np.ndarray

    def solve(self, u_b):
        """The interior displacement ``(3 n_i,)`` solving ``K_ii u_i = -K_ib u_b`` for the
        boundary displacement ``u_b`` ``(3 n_b,)`` mm (or ``(3 n_b, k)`` columns)."""
        return self.lu.solve(-(self.k_ib @ u_b))


def interior_solver(k, boundary, interior) -> InteriorSolver:
    """SciPy's reference interior solve of a global stiffness ``k`` (``(3N, 3N)`` sparse,
    :func:`stiffness_matrix`) with the ``boundary`` nodes ``(n_b,)`` held (Dirichlet) and
    the ``interior`` nodes ``(n_i,)`` free: one sparse LU of ``K_ii``.

    Raises
    ------
    RuntimeError
        ``K_ii`` singular (SciPy's ``splu``): a mesh or parameters without stiffness.
    """
    bd, idf = node_dofs(boundary), node_dofs(interior)
    k = sp.csr_matrix(k)
    return InteriorSolver(spla.splu(sp.csc_matrix(k[idf][:, idf])), k[idf][:, bd], bd, idf)


def strain_energy(nodes, tets, u, lam, mu):
    """Linear-elastic strain energy ``E_r`` (paper Eqs. 2-3).

    Parameters
    ----------
    nodes : (N, 3) array_like
        World mm.
    tets : (M, 4) array_like of int
    u : (N, 3) array_like
        Nodal displacements, mm.
    lam, mu : float or (M,) array_like
        Finite, ``>= 0``.

    Returns
    -------
    float
        ``sum_e V_e (mu eps:eps + lam/2 tr(eps)^2)`` = ``u^T K u / 2``, in ``[lam] mm^3``.

    Raises
    ------
    ValueError
        As :func:`element_stiffness`, or ``u`` not of shape ``(N, 3)``.
    """
    nodes, tets = check_mesh(nodes, tets)
    u = np.asarray(u, dtype=np.float64)
    if u.shape != nodes.shape:
        raise ValueError(f"u must have shape {nodes.shape}, got {u.shape}")
    g, vol = shape_gradients(nodes, tets)
    m = len(vol)
    dens = strain_energy_density(
        jnp.asarray(g), jnp.asarray(u[tets]), _per_element(lam, m, "lam"), _per_element(mu, m, "mu")
    )
    return float(np.sum(np.abs(vol) * np.asarray(dens)))


def strain_energy_density(grads, u_e, lam, mu):
    """Energy density per element ``mu eps:eps + lam/2 (div u)^2`` (paper Eq. 2 integrand).

    Parameters
    ----------
    grads : (M, 4, 3) array
        Shape-function gradients.
    u_e : (M, 4, 3) array
        Displacements of each element's nodes, mm.
    lam, mu : (M,) array

    Returns
    -------
    (M,) jax array
        Constant within each linear element.
    """
    du = jnp.sum(u_e[:, :, :, None] * grads[:, :, None, :], axis=1)  # du[i, j] = d u_i / d x_j
    eps = 0.5 * (du + jnp.swapaxes(du, 1, 2))
    tr = eps[:, 0, 0] + eps[:, 1, 1] + eps[:, 2, 2]
    return mu * jnp.sum(eps * eps, axis=(1, 2)) + 0.5 * lam * tr * tr


def element_strain_energy(grads, volumes, u_e, lam, mu):
    """JAX strain energy ``E_r`` summed over elements (see :func:`strain_energy`)."""
    return jnp.sum(volumes * strain_energy_density(grads, u_e, lam, mu))


