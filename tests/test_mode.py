"""The mode search (bayesreg.inference.mode)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayesreg.data.images import Image
from bayesreg.inference.mode import find_mode
from bayesreg.model.parameters import ParamLayout
from bayesreg.model.posterior import build_posterior
from conftest import box_mesh, compilations
from helpers import box_skull, log_p


def test_find_mode_reaches_a_stationary_point_from_a_far_start(small):
    """``find_mode`` (u_b alone, then u_b and log(phi) jointly): from a start with
    one ``lam`` at 97% of its prior range the returned point gains log p and its gradient
    in the search coordinates ``(u_b, log phi)`` has fallen by four orders of magnitude."""
    mesh = box_mesh((3, 3, 3), size=(30.0, 30.0, 30.0))
    layout = ParamLayout(("csf", "gm", "wm"), free=(("lam", 0), ("lam", 1), ("lam", 2)),
                         fixed=(("mu", 0, 1.0), ("mu", 1, 1.0), ("mu", 2, 1.0)))
    phi = np.array([5.0, 10.0, 97.0])
    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (1.0, 1.0, 0.0, 10.0)}
    _, base, theta = small  # its image term and skull, with lam alone free
    post = build_posterior(mesh, base.similarity, box_skull(), t_s=0.5, t_r=3.0, layout=layout, element_group=mesh.tissue,
                           prior=prior, phi_ref=phi)
    theta = np.concatenate([theta[: 3 * len(mesh.boundary)], phi])
    with compilations() as compiled:
        res = find_mode(post, theta, iterations=600)
    mode = res.theta
    assert compiled.get("jit(step)") == 1  # both stages (u_b alone, then joint) share one program
    nb3 = 3 * len(mesh.boundary)

    def grad_search(th):  # gradient in (u_b, log phi): d/d log phi = phi d/d phi
        g = np.asarray(jax.grad(lambda t: log_p(post, t)[0])(jnp.asarray(th)))
        return np.concatenate([g[:nb3], th[nb3:] * g[nb3:]])

    assert res.logp_mode > res.logp_start
    assert float(log_p(post, mode)[0]) == pytest.approx(res.logp_mode, rel=1e-9)
    assert np.all((mode[nb3:] > 0) & (mode[nb3:] < 100))
    assert np.linalg.norm(grad_search(mode)) <= 1e-4 * np.linalg.norm(grad_search(theta))


def _exact_log_p(post, theta):
    from bayesreg.model.posterior import log_normaliser, split_position

    phi = split_position(post, jnp.asarray(theta))[1]
    return float(log_p(post, theta)[0]) + float(log_normaliser(post, phi))


def test_a_misleading_normaliser_surrogate_is_caught_by_the_exact_log_p(monkeypatch):
    """With ``exact`` the parameters are optimised on rounds of the normaliser's surrogate,
    each kept only where the exact ``log p`` rose.  A surrogate made to mislead (its value
    less ``60 sum log phi``, which drives the parameters toward 0) is caught: the search
    falls back to the exact gradient and ends at the honest surrogate's mode, and both
    report the exact ``log p`` of the point they return."""
    import bayesreg.inference.mode as mode

    from helpers import box_posterior

    # priors whose mode is inside their support (with the uniform prior of `small` mu_wm
    # creeps onto its upper edge)
    prior = {"lam": (2.0, 3.0, 0.0, 100.0), "mu": (2.0, 3.0, 0.0, 10.0)}
    _, post, theta = box_posterior(prior, 3.0, np.array([1.0, 10.0, 30.0, 0.5, 1.0]))
    honest = find_mode(post, np.array(theta), iterations=400, exact=True)
    from bayesreg.model.posterior import log_normaliser

    original = mode.surrogate_normaliser

    def misleading(p, s, phi):
        return original(p, s, phi) - 60.0 * jnp.sum(jnp.log(phi))

    monkeypatch.setattr(mode, "surrogate_normaliser", misleading)  # in the objective
    monkeypatch.setattr(mode, "_normaliser_gap",  # and in the exact values (jitted at import)
                        jax.jit(lambda p, s, phi: log_normaliser(p, phi) - misleading(p, s, phi)))
    from conftest import compilations

    with compilations() as compiled:
        misled = find_mode(post, np.array(theta), iterations=400, exact=True)
    # the exact search that the misled rounds fall back to runs on their compiled L-BFGS step
    # (a second program made the CLI's one-compilation count depend on the rounds' luck)
    assert compiled.get("jit(step)") == 1, compiled
    for res in (honest, misled):
        assert res.logp_mode == pytest.approx(_exact_log_p(post, res.theta), rel=1e-9)
    nb3 = post.n_displacement
    np.testing.assert_allclose(misled.theta[nb3:], honest.theta[nb3:], rtol=1e-2)
    assert misled.logp_mode == pytest.approx(honest.logp_mode, abs=1e-2)
