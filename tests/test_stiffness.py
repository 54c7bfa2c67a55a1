"""The elastic operator in sliced ELL blocks (bayesreg.fem.stiffness) against SciPy's assembly."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.fem import element as fem
from bayesreg.fem import stiffness
from conftest import box_mesh


def test_build_operator_rejects_bad_boundary_indices():
    """Negative, out-of-range, fractional, repeated or no boundary indices, a 2-D array and a
    boolean mask of the wrong length are refused with the reason; a boolean mask of length
    N and integral floats give the operator of the indices."""
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
