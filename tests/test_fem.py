"""Finite elements: analytic cases (patch test, rigid modes, symmetry, hand computation)."""

import numpy as np
import pytest

from bayesreg import fem, stiffness
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
    """Fractional tets were truncated, string tets gave a UFuncTypeError, and a NaN node
    fooled the degenerate-element check; integral floats stay accepted."""
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


def test_build_operator_rejects_bad_boundary_indices():
    """Negative indices wrapped, floats were truncated, a bool mask was read as indices 0
    and 1, duplicates and an empty boundary were accepted, out-of-range gave an IndexError."""
    m = box_mesh((2, 2, 2))
    b, n = m.boundary, len(m.nodes)
    cases = [
        (np.r_[b[:-1], -1], r"boundary node indices must lie in \[0, 27\), got values -1\.\.25"),
        (np.r_[b, 10 ** 6], r"must lie in \[0, 27\), got values 0\.\.1000000"),
        (b + 0.3, "boundary must hold integer node indices.*non-integral"),
        (np.r_[b, b[0]], r"boundary node indices must be distinct, got repeated index\(es\) \[0\]"),
        (np.array([], int), "boundary must hold at least one node index"),
        (b[None], r"boundary must be a 1-D array .* got shape \(1, 26\)"),
        (np.ones(5, bool), r"boolean boundary mask must have shape \(27,\) .*got \(5,\)"),
    ]
    for boundary, match in cases:
        with pytest.raises(ValueError, match=match):
            stiffness.build_operator(m.nodes, m.tets, boundary)
    # a boolean mask of length N and integral floats give the operator of the indices
    mask = np.zeros(n, bool)
    mask[b] = True
    op, interior = stiffness.build_operator(m.nodes, m.tets, b)
    for other in (mask, b.astype(float)):
        op2, interior2 = stiffness.build_operator(m.nodes, m.tets, other)
        np.testing.assert_array_equal(interior2, interior)
        np.testing.assert_array_equal(np.asarray(op2.boundary), b)
        np.testing.assert_array_equal(np.asarray(op2.slot_ib), np.asarray(op.slot_ib))
    assert op.n_boundary == len(b)


def test_operator_blocks_check_the_parameter_shapes():
    m = box_mesh((1, 1, 1))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    lam = np.ones(len(m.tets))
    with pytest.raises(ValueError, match=r"lam_e must have shape \(6,\) \(one value per element\), got \(5,\)"):
        op.blocks(lam[:-1], lam)
    with pytest.raises(ValueError, match=r"mu_e must have shape \(6,\) .* got \(\)"):
        op.blocks(lam, 1.0)


def test_ell_operator_matches_scipy_blocks():
    import jax.numpy as jnp

    m = box_mesh((3, 3, 3))
    lam = np.linspace(1.0, 30.0, len(m.tets))
    mu = np.linspace(0.5, 2.0, len(m.tets))
    op, interior = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    k = fem.stiffness_matrix(m.nodes, m.tets, lam, mu)
    idf = (3 * interior[:, None] + np.arange(3)).ravel()
    bd = (3 * m.boundary[:, None] + np.arange(3)).ravel()
    k_ii, k_ib = k[idf][:, idf].toarray(), k[idf][:, bd].toarray()
    b_ii, b_ib = op.blocks(jnp.asarray(lam), jnp.asarray(mu))
    rng = np.random.default_rng(1)
    xi = rng.normal(size=(len(interior), 3))
    xb = rng.normal(size=(len(m.boundary), 3))
    np.testing.assert_allclose(
        np.asarray(stiffness.ell_matvec(b_ii, op.cols_ii, op.row_ii, jnp.asarray(xi))).ravel(),
        k_ii @ xi.ravel(), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(
        np.asarray(stiffness.ell_matvec(b_ib, op.cols_ib, op.row_ib, jnp.asarray(xb))).ravel(),
        k_ib @ xb.ravel(), rtol=1e-12, atol=1e-10)
    # the dense forms and the diagonal blocks of the sliced layout
    np.testing.assert_allclose(np.asarray(stiffness.ell_dense(b_ii, op.cols_ii, op.row_ii, len(interior))),
                               k_ii, rtol=0, atol=1e-12 * np.abs(k_ii).max())
    np.testing.assert_allclose(np.asarray(stiffness.ell_dense(b_ib, op.cols_ib, op.row_ib, len(m.boundary))),
                               k_ib, rtol=0, atol=1e-12 * np.abs(k_ib).max())
    diag = np.stack([k_ii[3 * r:3 * r + 3, 3 * r:3 * r + 3] for r in range(len(interior))])
    np.testing.assert_allclose(np.asarray(stiffness.ell_diagonal(b_ii, op.row_ii)), diag, rtol=1e-14)


def test_sliced_ell_layout_stores_every_block_once_and_little_padding():
    """Every nonzero 3x3 block of K_ii and K_ib has one slot; rows sorted by degree into
    ELL_SLICES slices, each as wide as its widest row; row_ii, row_ib are permutations."""
    m = box_mesh((4, 3, 3))
    op, interior = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    n_i, n_b = len(interior), len(m.boundary)
    k = fem.stiffness_matrix(m.nodes, m.tets, 1.0, 1.0)
    pattern = (abs(k) > 0).astype(int)
    blk = np.zeros((len(m.nodes), len(m.nodes)), bool)
    for a in range(3):
        for b in range(3):
            blk |= pattern[a::3, b::3].toarray() > 0
    for cols, rows, other, n_col in ((op.cols_ii, op.row_ii, interior, n_i),
                                     (op.cols_ib, op.row_ib, np.asarray(m.boundary), n_b)):
        assert len(cols) == stiffness.ELL_SLICES
        np.testing.assert_array_equal(np.sort(np.asarray(rows)), np.arange(n_i))
        c = [np.asarray(x) for x in cols]
        degree = np.concatenate([(x < n_col).sum(1) for x in c])
        assert np.all(np.diff(degree) <= 0)                      # sorted, decreasing
        assert all(x.shape[1] == max(1, (x < n_col).sum(1).max()) for x in c)
        want = blk[np.ix_(interior, other)].sum(1)               # blocks per interior row
        np.testing.assert_array_equal(degree[np.asarray(rows)], want)
    # the diagonal block in slot 0 of every K_ii row
    first = np.concatenate([np.asarray(x)[:, 0] for x in op.cols_ii])[np.asarray(op.row_ii)]
    np.testing.assert_array_equal(first, np.arange(n_i))


def test_group_blocks_combine_to_the_element_assembly():
    import jax
    import jax.numpy as jnp

    m = box_mesh((3, 3, 3))
    op, _ = stiffness.build_operator(m.nodes, m.tets, m.boundary)
    group = np.arange(len(m.tets)) % 3
    gb = stiffness.group_blocks(op, group, 3)
    assert [a.shape for a in gb.lam_ii] == [(3,) + c.shape + (3, 3) for c in op.cols_ii]
    assert [a.shape for a in gb.mu_ib] == [(3,) + c.shape + (3, 3) for c in op.cols_ib]
    lam_g, mu_g = np.array([0.7, 12.0, 31.0]), np.array([0.3, 1.0, 2.5])
    want = op.blocks(jnp.asarray(lam_g[group]), jnp.asarray(mu_g[group]))
    got = gb.combine(jnp.asarray(lam_g), jnp.asarray(mu_g))
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-13 * scale)
    with pytest.raises(ValueError, match="group must have shape"):
        stiffness.group_blocks(op, group[:-1], 3)
    with pytest.raises(ValueError, match="group must have shape"):
        stiffness.group_blocks(op, group, 2)
