"""The paper's constrained ground truth: elastic-energy minimiser under the skull (Sec. 4.1).

:func:`constrained_shift` pushes some boundary nodes toward the centre of gravity
(Dirichlet) and puts every other boundary node where it minimises the linear-elastic
strain energy subject to the skull constraint (frictionless contact: nodes may slide along
the skull, never enter it), by an augmented-Lagrangian method with semi-smooth Newton inner
solves on the Schur complement of ``K``.  The skull is the samplers' own smooth signed
distance (:mod:`bayesreg.mesh.constraints`), evaluated with its gradient and Hessian by
:class:`bayesreg.mesh.constraints.SignedDistance`.

Units: world mm; energies in ``[lam] mm^3``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from bayesreg.mesh.constraints import SignedDistance, skull_constraint
from bayesreg.fem.element import stiffness_matrix
from bayesreg.data.images import Image
from bayesreg.mesh.tetmesh import Mesh, signed_volumes
from bayesreg.truth.synthetic import Truth, centre_of_gravity, top_boundary

__all__ = ["constrained_shift"]


def constrained_shift(mesh: Mesh, lam_e, mu_e, forbidden: Image, *, shift_mm=15.0, n_pushed=20,
                      pushed=None, clearance_mm=None, tol_mm=1e-3, min_volume_ratio=0.05,
                      max_iter=100, load_steps=None) -> tuple[Truth, dict]:
    """Synthetic brain shift of paper Sec. 4.1: elastic-energy minimiser under the skull.

    ``P`` pushed boundary nodes move ``shift_mm`` toward the volume-weighted centre of
    gravity of the mesh (Dirichlet).  Every other boundary node takes the configuration
    that minimises the linear-elastic strain energy ``E = u^T K u / 2`` subject to the skull
    constraint: no node (boundary or interior) may end in the forbidden region; nodes may
    slide along it (frictionless contact).  Interior nodes always satisfy
    ``K_ii u_i = -K_ib u_b``, so the unknowns are the free boundary displacements and
    ``E = u_b^T S u_b / 2`` with ``S`` the (dense) Schur complement, built with a sparse LU
    (SuperLU) of ``K_ii`` - direct, so the paper's CSF values (1e-6 against 1-30) are fine.

    Method (tolerances in brackets).  The forbidden region is the samplers' smooth signed
    distance ``d(x)`` (mm, > 0 inside; :func:`bayesreg.mesh.constraints.skull_constraint` given
    the mesh at rest: the allowed voxels not connected to the undeformed nodes count as
    forbidden, since nodes cannot cross the skull; a C2 cubic B-spline, evaluated with its
    exact gradient and Hessian).  With ``g_n(u) = d(x_n + u_n) + c_n <= 0`` for every non-pushed node
    (``c_n`` the clearance) an augmented-Lagrangian (method of multipliers) loop solves the
    problem: for fixed multipliers ``l_n >= 0`` (contact forces) the merit
    ``E + sum_n [max(0, l_n + r g_n)^2 - l_n^2] / (2 r)`` is minimised by semi-smooth
    Newton - Hessian ``S + sum_{active} T_n^T (r grad d grad d^T + z_n Hess d) T_n``,
    ``z_n = l_n + r g_n``, ``T_n = du_n/du_f`` (the Hessian of ``d`` is replaced by its PSD
    part where the sum is not positive definite), dense Cholesky, Armijo backtracking - to
    ``max |grad| <= 1e-9 max |grad E(u_f = 0)|``; then ``l <- max(0, l + r g)`` and
    ``r <- 10 r`` when the violation did not drop fourfold.  ``r = rho * mean(diag S)``,
    so ``rho`` (start 10) is dimensionless.  Converged when ``max_n g_n <= tol_mm``; after
    ``max_iter`` outer iterations it returns unconverged, with the figures.

    Load stepping.  The skull region is not convex (ridges of the skull base, the dura's
    sheets), so the constrained minimiser is only a local one and which one depends on the
    path.  The push is applied in ``load_steps`` equal increments (quasi-static contact):
    each increment starts from the last solution plus the increment's unconstrained
    response, with the contact forces carried over, so no node moves by more than about
    one increment's push between two solutions and none jumps across a thin part of the
    skull to the far side, where the unconstrained minimiser would have put it and the
    samplers, which move continuously, could never follow.

    Clearance.  ``c`` defaults to half the voxel diagonal: the truth's nodes stop that far in
    front of the skull, so that a sampler's smooth barrier (``model.skull_barrier_mm``, 1 mm
    in the NUTS configs: ``-(w / s - 1)^3`` at clearance ``s``) barely sees them.  The
    result is checked with the samplers' own rule (``d < 0``,
    :func:`bayesreg.mesh.constraints.points_forbidden`): a node failing it gets its clearance
    raised by ``h / 2`` (``h`` the smallest spacing) and the loop goes on
    (``n_clearance_raises``), so a converged result has ``n_forbidden_nodes == 0``.  A node
    that is closer than ``c`` to the skull already at rest gets its rest distance as its
    clearance (never negative): the margin must not push the brain inward where the mesh
    (after :func:`bayesreg.mesh.meshing.carve_skull`) already touches the skull.

    Parameters
    ----------
    mesh : Mesh
        (N nodes, M elements, world mm)
    lam_e, mu_e : (M,) array_like
        per-element Lamé parameters, [lam] (e.g. kPa)
    forbidden : Image
        ``data > 0`` marks the skull; points outside the grid are forbidden
    shift_mm : float
        displacement of the pushed nodes, mm (> 0)
    n_pushed : int
        number of pushed nodes when ``pushed`` is None: the boundary nodes of
        largest world z (top of the head, supine craniotomy), as :func:`bayesreg.truth.synthetic.brain_shift`
    pushed : (P,) array_like of int, optional
        node indices, all boundary nodes (sorted,
        duplicates dropped)
    clearance_mm : float, optional
        ``c`` above (default half the voxel diagonal of
        ``forbidden``), >= 0
    tol_mm : float
        tolerance on the constraint violation ``max g_n``, mm (> 0)
    max_iter : int
        augmented-Lagrangian (outer) iterations per load step (>= 1)
    load_steps : int, optional
        increments of the push (>= 1; default ``ceil(shift_mm / h)``, ``h`` the smallest
        voxel spacing of ``forbidden``)

    Returns
    -------
    truth : Truth
        ``u`` (N, 3) mm, ``lam_e``, ``mu_e``, ``pushed`` (P,)
    info : dict (JSON-serialisable)
        ``energy`` and ``energy_unconstrained`` (same pushed nodes, no skull), [lam] mm^3;
        ``max_violation_mm`` = max over the non-pushed nodes of ``d(x_n + u_n)`` (> 0: in
        the skull; about ``-clearance`` at a contact; None without such nodes);
        ``max_violation_pushed_mm`` the same
        for the pushed nodes (not constrained); ``max_constraint_mm`` = ``max g_n`` over
        the constrained nodes (``<= tol_mm`` when converged: ``d_n <= -c_n``, where ``c_n``
        is below ``clearance`` for a node nearer the skull at rest); ``n_forbidden_nodes``
        (every node, by the samplers' rule :func:`bayesreg.mesh.constraints.points_forbidden`
        against the plain skull); ``n_active`` (nodes with
        ``g_n >= -tol_mm``); ``iterations`` (outer), ``newton_iterations`` (total);
        ``penalty`` (final dimensionless ``rho``); ``converged``; ``load_steps``;
        ``load_factor`` (1 when converged: the fraction of the push reached, the pushed nodes
        at ``load_factor * shift_mm``, where a step did not converge); ``n_inverted`` (deformed
        elements with signed volume <= 0); ``clearance_mm``; ``n_clearance_raises``;
        ``tol_mm``; ``pushed``; ``shift_mm``.

    Raises
    ------
    ValueError
        ``shift_mm <= 0``, ``tol_mm <= 0``, ``clearance_mm < 0``, ``max_iter < 1``,
        ``load_steps`` not an integer >= 1,
        ``n_pushed`` outside ``[1, n_b]``, ``pushed`` empty or not boundary nodes,
        ``lam_e``/``mu_e`` not of shape ``(M,)``, ``forbidden`` not 3D, or a pushed node's
        target in the forbidden region or beyond it (the nodes are named).

    References
    ----------
    Risholm, Samset, Wells, "Bayesian Estimation of Deformation and Elastic Parameters in
    Non-rigid Registration", Sec. 4.1 (the synthetic dataset: 20 boundary nodes fixed with
    a 15 mm shift toward the centre of gravity, the other boundary nodes at the minimum of
    the elastic energy).  Nocedal & Wright, *Numerical Optimization*, 2nd ed., Sec. 17.3-17.4
    (augmented Lagrangian for inequality constraints).
    """
    nodes = np.asarray(mesh.nodes, np.float64)
    tets = np.asarray(mesh.tets)
    n, m = len(nodes), len(tets)
    lam_e = np.asarray(lam_e, np.float64)
    mu_e = np.asarray(mu_e, np.float64)
    if lam_e.shape != (m,) or mu_e.shape != (m,):
        raise ValueError(f"lam_e and mu_e must have shape ({m},), got {lam_e.shape}, {mu_e.shape}")
    if not shift_mm > 0:
        raise ValueError(f"shift_mm must be > 0, got {shift_mm}")
    if not tol_mm > 0:
        raise ValueError(f"tol_mm must be > 0, got {tol_mm}")
    if not 0 <= min_volume_ratio < 1:
        raise ValueError(f"min_volume_ratio must be in [0, 1), got {min_volume_ratio}")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if load_steps is not None and not (int(load_steps) == load_steps and load_steps >= 1):
        raise ValueError(f"load_steps must be an integer >= 1, got {load_steps}")
    mask = np.asarray(forbidden.data) > 0
    if mask.ndim != 3:
        raise ValueError(f"forbidden must be 3D, got shape {mask.shape}")
    affine = np.asarray(forbidden.affine, np.float64)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    if clearance_mm is None:
        clearance_mm = 0.5 * float(np.linalg.norm(spacing))
    if not clearance_mm >= 0:
        raise ValueError(f"clearance_mm must be >= 0, got {clearance_mm}")
    n_steps = (int(load_steps) if load_steps is not None
               else max(1, int(np.ceil(shift_mm / spacing.min()))))
    boundary = np.asarray(mesh.boundary)
    if pushed is None:
        pushed = boundary[top_boundary(mesh, n_pushed)]
    else:
        pushed = np.unique(np.asarray(pushed, np.int64).ravel())
        if pushed.size == 0:
            raise ValueError("pushed must name at least one node")
        bad = np.setdiff1d(pushed, boundary)
        if bad.size:
            raise ValueError(f"pushed nodes {bad.tolist()} are not boundary nodes")
    cog = centre_of_gravity(mesh)
    direction = cog - nodes[pushed]
    u_p = shift_mm * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    # the samplers' skull, plain and with the pockets beyond it (admissible: the allowed
    # voxels connected to the undeformed nodes)
    plain = SignedDistance(skull_constraint(forbidden))
    sdf = SignedDistance(skull_constraint(forbidden, nodes=nodes))
    bad = pushed[plain(nodes[pushed] + u_p)[0] >= 0]
    if bad.size:
        raise ValueError(
            f"the target of pushed node(s) {bad.tolist()} lies in the forbidden region; "
            "lower shift_mm or choose other nodes"
        )
    bad = pushed[sdf(nodes[pushed] + u_p)[0] >= 0]
    if bad.size:
        raise ValueError(
            f"the target of pushed node(s) {bad.tolist()} lies beyond the forbidden region "
            "(an allowed pocket not connected to the undeformed mesh)"
        )

    # condensation: u = u0 + T u_f, u_f the free boundary DOFs
    k = sp.csr_matrix(stiffness_matrix(nodes, tets, lam_e, mu_e))
    is_p = np.zeros(n, bool)
    is_p[pushed] = True
    is_b = np.zeros(n, bool)
    is_b[boundary] = True
    free = np.flatnonzero(is_b & ~is_p)
    interior = np.flatnonzero(~is_b)

    def dofs(ix):
        return (3 * ix[:, None] + np.arange(3)).ravel()

    df, dp, di = dofs(free), dofs(pushed), dofs(interior)
    nf = df.size
    t_mat = np.zeros((3 * n, nf))
    t_mat[df, np.arange(nf)] = 1.0
    u0 = np.zeros(3 * n)
    u0[dp] = u_p.ravel()
    if di.size:
        lu = spla.splu(sp.csc_matrix(k[di][:, di]))
        t_mat[di] = -lu.solve(k[di][:, df].toarray())
        u0[di] = -lu.solve(k[di][:, dp] @ u0[dp])
    kt = k @ t_mat
    s_mat = t_mat.T @ kt
    s_mat = 0.5 * (s_mat + s_mat.T)
    load = t_mat.T @ (k @ u0)  # dE/du_f at u_f = 0
    e0 = 0.5 * u0 @ (k @ u0)
    scale = float(np.mean(np.diag(s_mat))) if nf else 1.0
    ridge = 1e-14 * scale * np.eye(nf)

    factor = [1.0]  # the load factor: the pushed nodes at factor[0] * u_p (load stepping)

    def energy(uf):
        f = factor[0]
        return 0.5 * uf @ (s_mat @ uf) + f * (load @ uf) + f * f * e0

    def cho(h):
        return sla.cho_factor(h + ridge)

    uf_free = -sla.cho_solve(cho(s_mat), load) if nf else np.zeros(0)
    energy_unc = energy(uf_free)

    cons = np.flatnonzero(~is_p)  # constrained nodes: free boundary + interior
    t3 = t_mat.reshape(n, 3, nf)[cons]
    x_c = nodes[cons]
    u0_c = u0.reshape(n, 3)[cons]
    # a node already closer to the skull at rest than the clearance keeps its rest distance
    # as its clearance (it must not be pushed inward by the margin itself)
    d_rest, _ = sdf(x_c)
    clear = np.minimum(float(clearance_mm), np.maximum(-d_rest, 0.0))
    gtol = 1e-9 * max(float(np.abs(load).max()) if nf else 0.0, 1e-300)

    def positions(uf):
        return x_c + factor[0] * u0_c + t3 @ uf

    # no element may shrink below min_volume_ratio of its rest volume: g_e = h_e (q - V_e / V0_e)
    # <= 0 with h_e = V0_e^(1/3), in mm like the skull constraint
    v_rest = signed_volumes(nodes, tets)
    h_e = np.cbrt(v_rest)
    t_nodes = t_mat.reshape(n, 3, nf)
    u0_n = u0.reshape(n, 3)

    def volume_g(uf):
        return h_e * (float(min_volume_ratio)
                      - signed_volumes(nodes + factor[0] * u0_n + t_nodes @ uf, tets) / v_rest)

    def volume_jac(uf, act):
        """``d g_e / d u_f`` of the elements ``act``, ``(len(act), nf)``."""
        tt = tets[act]
        x = nodes[tt] + factor[0] * u0_n[tt] + t_nodes[tt] @ uf  # (A, 4, 3)
        a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        dv = np.stack([np.zeros_like(a), np.cross(b, c), np.cross(c, a), np.cross(a, b)], 1) / 6.0
        dv[:, 0] = -dv[:, 1:].sum(1)
        jac = np.einsum("eai,eaif->ef", dv, t_nodes[tt])
        return -(h_e[act] / v_rest[act])[:, None] * jac

    def merit(uf, lmb, lmb_v, r):
        d, grad = sdf(positions(uf))
        z = np.maximum(0.0, lmb + r * (d + clear))
        gv = volume_g(uf)
        zv = np.maximum(0.0, lmb_v + r * gv)
        return (energy(uf) + (z @ z - lmb @ lmb + zv @ zv - lmb_v @ lmb_v) / (2 * r),
                z, grad, d, zv, gv)

    def newton_factor(uf, act, grad, z, r, jac_v):
        # S + sum_active T_n^T (r grad grad^T + z_n Hess d) T_n + r J_v^T J_v (Gauss-Newton for
        # the element volumes), Cholesky-factorised; where that is not positive definite,
        # each Hess d is replaced by its PSD part
        _, _, hess = sdf(positions(uf)[act], hessian=True)
        ta = t3[act]
        base = s_mat + r * (jac_v.T @ jac_v)
        for psd in (False, True):
            if psd:
                ev, vec = np.linalg.eigh(hess)
                hess = np.einsum("nij,nj,nkj->nik", vec, np.maximum(ev, 0.0), vec)
            blocks = r * grad[act, :, None] * grad[act, None, :] + z[act, None, None] * hess
            h = base + ta.reshape(-1, nf).T @ np.matmul(blocks, ta).reshape(-1, nf)
            try:
                return cho(h)
            except np.linalg.LinAlgError:
                if psd:
                    raise

    def augmented_lagrangian(uf, lmb, lmb_v):
        """The constrained minimiser at the current load factor from ``uf`` and the
        multipliers: ``(uf, lmb, lmb_v, converged, outer, newton, raises)``."""
        rho, viol_prev, converged, n_newton, n_raise, it = 10.0, np.inf, False, 0, 0, 0
        for it in range(1, int(max_iter) + 1):
            r = rho * scale
            phi, z, grad, d, zv, gv = merit(uf, lmb, lmb_v, r)
            for _ in range(100):
                act = np.flatnonzero(z > 0)
                act_v = np.flatnonzero(zv > 0)
                jac = np.matmul(grad[act, None, :], t3[act])[:, 0]
                jac_v = volume_jac(uf, act_v)
                gphi = s_mat @ uf + factor[0] * load + jac.T @ z[act] + jac_v.T @ zv[act_v]
                if gphi.size == 0 or np.abs(gphi).max() <= gtol:
                    break
                step = -sla.cho_solve(newton_factor(uf, act, grad, z, r, jac_v), gphi)
                n_newton += 1
                slope = gphi @ step
                a = 1.0
                while True:
                    phi_new, *rest = merit(uf + a * step, lmb, lmb_v, r)
                    # Armijo; a decrease below round-off of phi is taken as is
                    if (phi_new <= phi + 1e-4 * a * slope or a < 1e-12
                            or -slope < 1e-13 * abs(phi)):
                        break
                    a *= 0.5
                uf = uf + a * step
                phi, (z, grad, d, zv, gv) = phi_new, rest
                if a < 1e-12:
                    break
            g = d + clear
            lmb = np.maximum(0.0, lmb + r * g)
            lmb_v = np.maximum(0.0, lmb_v + r * gv)
            viol = max(float(g.max()) if g.size else -np.inf, float(gv.max()))
            if viol <= tol_mm:
                u_all = (factor[0] * u0 + t_mat @ uf).reshape(n, 3)
                bad = sdf(x_c + u_all[cons])[0] >= 0
                if not bad.any():
                    converged = True
                    break
                clear[bad] += 0.5 * spacing.min()
                n_raise += 1
                viol_prev = np.inf
                continue
            if viol > 0.25 * viol_prev:
                rho *= 10.0
            viol_prev = viol
        return uf, lmb, lmb_v, converged, it, n_newton, n_raise, rho

    uf = np.zeros(nf)
    lmb = np.zeros(cons.size)
    lmb_v = np.zeros(m)
    n_newton = 0
    n_raise = 0
    n_outer = 0
    for j in range(1, n_steps + 1):
        # load stepping: the push in n_steps increments, each from the last one's solution
        # plus the increment's unconstrained response (the contact forces carried over), so
        # that no node crosses a thin part of the skull between two solutions
        uf = uf + uf_free / n_steps
        factor[0] = j / n_steps
        uf, lmb, lmb_v, converged, it, newton, raised, rho = augmented_lagrangian(uf, lmb, lmb_v)
        n_newton, n_raise, n_outer = n_newton + newton, n_raise + raised, n_outer + it
        if not converged:
            break

    u = (u0 * factor[0] + t_mat @ uf).reshape(n, 3)
    u[pushed] = u_p * factor[0]
    d_all, _ = sdf(nodes + u)
    g = d_all[cons] + clear
    info = {
        "energy": float(0.5 * u.ravel() @ (k @ u.ravel())),
        "energy_unconstrained": float(energy_unc),
        "max_violation_mm": float(d_all[cons].max()) if cons.size else None,
        "max_violation_pushed_mm": float(d_all[pushed].max()),
        "max_constraint_mm": float(g.max()) if cons.size else None,
        "n_forbidden_nodes": int(np.sum(plain(nodes + u)[0] >= 0)),
        "n_active": int(np.sum(g >= -tol_mm)),
        "iterations": int(n_outer),
        "load_steps": int(n_steps),
        "load_factor": float(factor[0]),
        "newton_iterations": int(n_newton),
        "penalty": float(rho),
        "converged": bool(converged),
        "n_inverted": int(np.sum(signed_volumes(nodes + u, tets) <= 0)),
        "min_volume_ratio": float(np.min(signed_volumes(nodes + u, tets) / v_rest)),
        "n_volume_active": int(np.sum(volume_g(uf) >= -tol_mm)),
        "clearance_mm": float(clearance_mm),
        "n_clearance_raises": int(n_raise),
        "tol_mm": float(tol_mm),
        "pushed": [int(p) for p in pushed],
        "shift_mm": float(shift_mm),
    }
    return Truth(u, lam_e, mu_e, pushed), info
