"""The chains' start (bayesreg.inference.initialisation): the Laplace precision of the condensed posterior."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from bayesreg.fem.element import stiffness_matrix
from bayesreg.inference.initialisation import laplace_precision
from bayesreg.model.posterior import elastic_groups
from bayesreg.model.problem import Problem
from helpers import box_posterior


@pytest.mark.parametrize("level, similarity", [(0, "ssd"), (1, "ssd"), (1, "lncc")])
def test_laplace_precision_is_the_gauss_newton_matrix_of_the_condensed_posterior(level, similarity,
                                                                               request):
    """``laplace_precision`` = ``2 J_b^T J_b / T_s + S / T_r`` (+ its small ridge), with
    ``J_b`` the Jacobian of the similarity term's residuals with respect to ``u_b`` through
    the interior map ``u_i = -K_ii^-1 K_ib u_b`` (here by ``jax.jacfwd`` and a dense solve):
    SSD's sparse Gram matrix and LNCC's generic one alike."""
    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    phi = np.array([1.0, 10.0, 30.0, 0.5, 1.0])
    # level 0: the shared ``small`` posterior (these prior, T_r and phi)
    mesh, post, theta = (request.getfixturevalue("small") if level == 0 else
                         box_posterior(prior, 3.0, phi, quadrature_level=level, similarity=similarity))
    problem = Problem(None, None, None, mesh, None, mesh.tissue, post, None, None, phi, 1.0, 0, {})
    prec = laplace_precision(problem, theta)
    lam_g, mu_g = (np.asarray(a) for a in elastic_groups(post, jnp.asarray(phi)))
    k = stiffness_matrix(mesh.nodes, mesh.tets, lam_g[mesh.tissue], mu_g[mesh.tissue]).toarray()
    bd, idf = (3 * mesh.boundary[:, None] + np.arange(3)).ravel(), (3 * mesh.interior[:, None] + np.arange(3)).ravel()
    h = -sla.solve(k[np.ix_(idf, idf)], k[np.ix_(idf, bd)], assume_a="pos")
    schur = k[np.ix_(bd, bd)] + k[np.ix_(idf, bd)].T @ h

    def residuals(u_b):
        u = jnp.zeros(3 * len(mesh.nodes)).at[bd].set(u_b).at[idf].set(jnp.asarray(h) @ u_b)
        return post.similarity.residuals(u.reshape(-1, 3)[mesh.tets]).ravel()

    nb3 = 3 * len(mesh.boundary)
    jac = np.asarray(jax.jacfwd(residuals)(jnp.asarray(theta[:nb3])))
    if similarity == "ssd":
        assert jac.shape == (len(mesh.tets) * 4 * 8**level, nb3)
    expected = 2.0 / 0.5 * jac.T @ jac + schur / 3.0
    ridge = 1e-6 * np.trace(expected) / nb3
    np.testing.assert_allclose(prec, expected + ridge * np.eye(nb3), rtol=1e-7,
                               atol=1e-9 * np.abs(expected).max())
