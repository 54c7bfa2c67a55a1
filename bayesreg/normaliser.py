"""The exact normaliser of the elastic prior: ``(1/2) log pdet S(lam, mu)``.

With the interior nodes at the FE solution, ``E_r = u_b^T S u_b / 2`` with
``S = K_bb - K_bi K_ii^-1 K_ib`` the Schur complement of ``K`` on the boundary DOFs, so the
prior ``exp(-E_r / T_r)`` of paper Eq. 12 is a Gaussian on ``u_b`` (on the complement of
the six rigid-body modes, the null space of ``S``) whose log-normaliser is
``(1/2) log pdet S - ((3 n_b - 6) / 2) log (2 pi T_r)``; the second term is constant.  The
paper drops the first (its Sec. 3.3), which biases the elastic parameters toward zero;
``model.prior_normaliser: exact`` adds it.

Computed from one dense float64 Cholesky factorisation of the stiffness with the rigid-body
modes of the boundary block lifted, interior DOFs first: ``K_aug = K + c P``,
``P = R_b R_b^T`` on the boundary block (``R_b`` orthonormal rigid modes, ``c`` the mean of
``diag K_bb``).  The trailing block of its factor is the Cholesky factor of ``S + c P``,
and ``det(S + c P) = c^6 pdet S`` because ``P`` projects onto the null space of ``S``.
Cost ``(3N)^3 / 3`` flops; differentiable by JAX.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["NormaliserData", "normaliser_data", "dense_stiffness", "log_pdet_schur",
           "add_normaliser"]


class NormaliserData(NamedTuple):
    """Static data of :func:`dense_stiffness` and :func:`log_pdet_schur`.

    Attributes
    ----------
    dense_index : (M * 144,) int
        Flat position in the dense ``(3N, 3N)`` stiffness, DOFs ordered interior nodes
        first (in the operator's row order) then boundary nodes, of each entry of the
        element matrices (``klam`` / ``kmu`` of :class:`bayesreg.stiffness.ElasticOperator`).
    rigid_b : (3 n_b, 6)
        Orthonormal basis of the rigid-body modes restricted to the boundary DOFs (the
        null space of the Schur complement ``S``).
    """

    dense_index: jax.Array
    rigid_b: jax.Array


def normaliser_data(nodes, tets, boundary, perm) -> NormaliserData:
    """:class:`NormaliserData` of a mesh.

    Parameters
    ----------
    nodes : (N, 3) array
        World mm.
    tets : (M, 4) int array
    boundary : (n_b,) int array
        Boundary node indices.
    perm : (N,) int array
        Position of each node in ``concat(boundary, interior)`` (boundary first).
    """
    n_b = len(boundary)
    perm = np.asarray(perm)
    n_i = len(perm) - n_b
    dense_pos = np.where(perm >= n_b, perm - n_b, perm + n_i)  # interior DOFs first
    dof = (3 * dense_pos[np.asarray(tets)][:, :, None] + np.arange(3)).reshape(-1, 12)
    n_dof = 3 * len(perm)
    dense_index = (dof[:, :, None] * n_dof + dof[:, None, :]).reshape(-1)
    xb = np.asarray(nodes, np.float64)[np.asarray(boundary)]
    xb = xb - xb.mean(axis=0)
    rigid = np.zeros((n_b, 3, 6))
    for k in range(3):
        rigid[:, k, k] = 1.0
        rigid[:, :, 3 + k] = np.cross(np.eye(3)[k], xb)
    rigid_b = np.linalg.qr(rigid.reshape(-1, 6))[0]
    return NormaliserData(
        dense_index=jnp.asarray(dense_index, dtype=jnp.int32 if n_dof**2 < 2**31 else jnp.int64),
        rigid_b=jnp.asarray(rigid_b))


def dense_stiffness(klam, kmu, lam_e, mu_e, data: NormaliserData, n_dof: int):
    """Dense stiffness ``K`` ``(3N, 3N)``, interior DOFs first (see
    :attr:`NormaliserData.dense_index`), from the unit element matrices ``klam``, ``kmu``
    and per-element Lamé parameters ``lam_e``, ``mu_e`` ``(M,)``.

    Memory ``72 N^2`` bytes: meant for meshes up to a few thousand nodes.
    """
    m = lam_e.shape[0]
    ke = (lam_e[:, None, None, None, None] * klam + mu_e[:, None, None, None, None] * kmu)
    ke = ke.transpose(0, 1, 3, 2, 4).reshape(m, 144)  # (a, i, b, j) -> rows 3a+i, cols 3b+j
    return jax.ops.segment_sum(ke.reshape(-1), data.dense_index,
                               num_segments=n_dof * n_dof).reshape(n_dof, n_dof)


def log_pdet_schur(k, rigid_b):
    """``(1/2) log pdet S`` of the dense stiffness ``k`` ``(3N, 3N)`` (interior DOFs first) on
    its trailing ``3 n_b`` boundary DOFs (module docstring).

    Returns
    -------
    () array
        ``NaN`` when the factorisation fails (``K`` not positive definite on the complement
        of the rigid modes: non-positive parameters).
    """
    nb3 = rigid_b.shape[0]
    k_bb = k[-nb3:, -nb3:]
    c = jax.lax.stop_gradient(jnp.mean(jnp.diag(k_bb)))  # any c > 0: the result does not depend on it
    k = k.at[-nb3:, -nb3:].add(c * rigid_b @ rigid_b.T)
    chol = jnp.linalg.cholesky(0.5 * (k + k.T))
    return jnp.sum(jnp.log(jnp.diag(chol)[-nb3:])) - 3.0 * jnp.log(c)


def add_normaliser(logp, log_norm):
    """``logp + log_norm``, ``-inf`` where either is not finite (a failed factorisation gives
    a NaN normaliser: that position is rejected like any other hard-constraint violation)."""
    return jnp.where(jnp.isfinite(logp) & jnp.isfinite(log_norm), logp + log_norm, -jnp.inf)
