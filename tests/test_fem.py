"""Finite elements: analytic cases (patch test, rigid modes, symmetry, hand computation)."""

import numpy as np
import pytest

from bayesreg.fem import element as fem
from bayesreg.fem import stiffness
from conftest import box_mesh


def rigid_modes(nodes):
    c = nodes - nodes.mean(0)
    modes = [np.tile(np.eye(3)[k], (len(nodes), 1)) for k in range(3)]
    for axis in np.eye(3):
        modes.append(np.cross(axis, c))
    return modes


def test_reference_tet_by_hand():
    # unit reference tet: grad N0 = (-1,-1,-1), grad N1 = e_x, ..., V = 1/6
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    tets = np.array([[0, 1, 2, 3]])
    k = fem.element_stiffness(nodes, tets, 2.0, 3.0)[0]
    lam, mu, v = 2.0, 3.0, 1.0 / 6.0
    # K[x of node1, x of node1] = V (lam + 2 mu) ; K[x of node1, y of node2] = V lam;
    # K[y of node1, x of node2] = V mu ; K[x of node0, x of node0] = V (lam + 2mu + 2mu)
    assert k[3, 3] == pytest.approx(v * (lam + 2 * mu))
    assert k[3, 7] == pytest.approx(v * lam)
    assert k[4, 6] == pytest.approx(v * mu)
    assert k[0, 0] == pytest.approx(v * (lam + 2 * mu + 2 * mu))
    assert k[3, 4] == pytest.approx(0.0)


def test_index_form_matches_voigt_btcb():
    m = box_mesh((2, 2, 2))
    rng = np.random.default_rng(0)
    lam = rng.uniform(0.5, 30, len(m.tets))
    mu = rng.uniform(0.1, 3, len(m.tets))
    a = fem.element_stiffness(m.nodes, m.tets, lam, mu)
    b = fem.element_stiffness_voigt(m.nodes, m.tets, lam, mu)
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


def test_patch_test_linear_field_constant_strain_and_energy():
    m = box_mesh((3, 2, 2), size=(30.0, 20.0, 20.0))
    grad = np.array([[0.01, 0.002, -0.003], [0.004, -0.02, 0.001], [0.0, 0.005, 0.015]])
    u = m.nodes @ grad.T  # u_i = sum_j grad[i, j] x_j
    g, vol = fem.shape_gradients(m.nodes, m.tets)
    du = np.einsum("mai,maj->mij", u[m.tets], g)
    np.testing.assert_allclose(du, np.broadcast_to(grad, du.shape), atol=1e-14)
    lam, mu = 7.0, 1.5
    eps = 0.5 * (grad + grad.T)
    expected = (mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2) * 30 * 20 * 20
    assert fem.strain_energy(m.nodes, m.tets, u, lam, mu) == pytest.approx(expected, rel=1e-12)
    k = fem.stiffness_matrix(m.nodes, m.tets, lam, mu)
    assert 0.5 * u.ravel() @ (k @ u.ravel()) == pytest.approx(expected, rel=1e-12)


def test_interior_solver_reproduces_a_linear_field_from_its_boundary_values():
    """Patch test of the Dirichlet split: a linear field held on the boundary nodes (given
    in a shuffled order) is solved exactly at the interior nodes (any order), its DOFs
    ``3*i + axis`` node-major."""
    m = box_mesh((3, 3, 3))
    grad = np.array([[0.01, 0.002, -0.003], [0.004, -0.02, 0.001], [0.0, 0.005, 0.015]])
    u = m.nodes @ grad.T + np.array([0.5, -1.0, 2.0])
    rng = np.random.default_rng(0)
    boundary, interior = rng.permutation(m.boundary), rng.permutation(m.interior)
    assert len(interior) == 8
    solver = fem.interior_solver(fem.stiffness_matrix(m.nodes, m.tets, 7.0, 1.5), boundary, interior)
    np.testing.assert_array_equal(solver.boundary_dofs, fem.node_dofs(boundary))
    np.testing.assert_array_equal(fem.node_dofs([2, 0]), [6, 7, 8, 0, 1, 2])
    np.testing.assert_allclose(solver.solve(u[boundary].ravel()), u[interior].ravel(), atol=1e-12)


def test_rigid_modes_have_zero_energy_and_span_nullspace():
    m = box_mesh((2, 2, 2))
    k = fem.stiffness_matrix(m.nodes, m.tets, 10.0, 1.0).toarray()
    for mode in rigid_modes(m.nodes):
        assert np.linalg.norm(k @ mode.ravel()) < 1e-10 * np.linalg.norm(k)
        assert fem.strain_energy(m.nodes, m.tets, mode, 10.0, 1.0) == pytest.approx(0.0, abs=1e-10)
    w = np.linalg.eigvalsh(k)
    assert np.sum(np.abs(w) < 1e-9 * w.max()) == 6  # exactly the six rigid-body modes
    assert w.min() > -1e-9 * w.max()  # positive semi-definite


def test_stiffness_symmetric_and_node_major_dofs():
    m = box_mesh((2, 1, 1))
    k = fem.stiffness_matrix(m.nodes, m.tets, np.linspace(1, 5, len(m.tets)), 1.0)
    assert abs(k - k.T).max() < 1e-12 * abs(k).max()
    # a pure x-translation of node 0 only loads x-DOFs consistently: K[:, 0] = K e_(3*0+0)
    e = np.zeros(k.shape[0])
    e[0] = 1.0
    np.testing.assert_allclose(k @ e, k.toarray()[:, 0])


def test_bad_shapes_raise():
    m = box_mesh((1, 1, 1))
    with pytest.raises(ValueError, match="nodes must have shape"):
        fem.stiffness_matrix(m.nodes[:, :2], m.tets, 1.0, 1.0)
    with pytest.raises(ValueError, match="lam must be"):
        fem.stiffness_matrix(m.nodes, m.tets, np.ones(3), 1.0)
    with pytest.raises(ValueError, match="outside"):
        fem.stiffness_matrix(m.nodes, m.tets + 100, 1.0, 1.0)


def test_mesh_with_non_integer_tets_or_non_finite_nodes_raises():
    """Fractional, string or boolean tets and NaN or infinite nodes are refused with the
    reason (the node named); integral floats are accepted as indices."""
    m = box_mesh((1, 1, 1))
    with pytest.raises(ValueError, match="tets must hold integer node indices.*non-integral"):
        fem.stiffness_matrix(m.nodes, m.tets + 0.5, 1.0, 1.0)
    with pytest.raises(ValueError, match="tets must hold integer node indices.*dtype <U"):
        fem.stiffness_matrix(m.nodes, m.tets.astype(str), 1.0, 1.0)
    with pytest.raises(ValueError, match="tets must hold integer node indices.*dtype bool"):
        fem.shape_gradients(m.nodes, m.tets > 0)
    k = fem.stiffness_matrix(m.nodes, m.tets.astype(float), 1.0, 1.0)
    assert abs(k - fem.stiffness_matrix(m.nodes, m.tets, 1.0, 1.0)).max() == 0
    for bad in (np.nan, np.inf):
        nodes = m.nodes.copy()
        nodes[3, 1] = bad
        with pytest.raises(ValueError, match=r"nodes must be finite, got NaN or inf at node\(s\) \[3\]"):
            fem.shape_gradients(nodes, m.tets)
        with pytest.raises(ValueError, match="nodes must be finite"):
            stiffness.build_operator(nodes, m.tets, m.boundary)


def test_negative_or_non_finite_lame_parameters_raise():
    """The host (NumPy) FE routines reject lam, mu < 0 or not finite (0 stays allowed: the
    unit parts ``element_stiffness(.., 1, 0)``); the JAX ones used by the log-density do not
    look at values."""
    m = box_mesh((1, 1, 1))
    u = np.zeros_like(m.nodes)
    with pytest.raises(ValueError, match="lam must be finite and >= 0, got -1.0"):
        fem.stiffness_matrix(m.nodes, m.tets, -1.0, 1.0)
    with pytest.raises(ValueError, match="mu must be finite and >= 0, got nan"):
        fem.strain_energy(m.nodes, m.tets, u, 1.0, np.nan)
    lam = np.ones(len(m.tets))
    lam[2] = -0.5
    with pytest.raises(ValueError, match=r"lam must be finite and >= 0, got -0.5 \(1 of 6 values bad\)"):
        fem.element_stiffness(m.nodes, m.tets, lam, 1.0)
    with pytest.raises(ValueError, match="mu must be finite and >= 0, got inf"):
        fem.element_stiffness_voigt(m.nodes, m.tets, 1.0, np.inf)
    assert np.all(np.isfinite(fem.element_stiffness(m.nodes, m.tets, 1.0, 0.0)))
