"""Targets from a config (bayesreg.inference.targets): the CG preconditioner chosen by size, memory and
device."""

from types import SimpleNamespace

import jax
import pytest

from bayesreg.inference import targets
from bayesreg.config import ConfigError, load_config
from bayesreg.inference.targets import cg_preconditioner, dense_preconditioning


def test_preconditioner_choice_follows_size_and_memory():
    """``solver.preconditioner: auto`` takes the spectral preconditioner where the posterior
    has one (one parameter group), else the dense one where its inverses fit (``3 n_i <=
    4096`` DOFs, at most 2 GiB for all chains), else block Jacobi; a bad value names the key."""

    def problem(n_interior, spectral=None):
        return SimpleNamespace(posterior=SimpleNamespace(op=SimpleNamespace(n_interior=n_interior),
                                                         spectral=spectral))

    cfg = load_config("configs/paper_three_compartment.yaml")
    assert cfg.solver.preconditioner == "auto"
    assert dense_preconditioning(problem(457), cfg)  # the paper's size: 7.5 MB a chain
    assert not dense_preconditioning(problem(2400), cfg)  # 7,200 DOFs
    assert not dense_preconditioning(problem(457), cfg, n_chains=1024)  # 7.7 GB in all
    assert cg_preconditioner(problem(2400), cfg) == "block-jacobi"
    assert not dense_preconditioning(problem(457, spectral=True), cfg)
    assert cg_preconditioner(problem(457, spectral=True), cfg) == "spectral"
    forced = load_config("configs/paper_three_compartment.yaml", overrides=["solver.preconditioner=dense"])
    assert dense_preconditioning(problem(2400), forced)
    off = load_config("configs/paper_three_compartment.yaml", overrides=["solver.preconditioner=block-jacobi"])
    assert not dense_preconditioning(problem(457), off)
    with pytest.raises(ConfigError, match=r"solver\.preconditioner"):
        load_config(None, overrides=["solver.preconditioner=ilu"])
    with pytest.raises(ConfigError, match=r"spectral needs one parameter group"):
        load_config("configs/paper_three_compartment.yaml", overrides=["solver.preconditioner=spectral"])
    load_config("configs/paper_uniform.yaml", overrides=["solver.preconditioner=spectral"])


def test_dense_budget_follows_the_device_memory(monkeypatch):
    """``auto``'s budget for the chains' dense inverses: 2 GiB on a CPU; on an accelerator a
    sixteenth of the memory it reports (an H200's 112.6 GB: dense at 256 chains of the paper's
    size, block Jacobi at 1,024), at least 2 GiB, and 2 GiB where the device reports no
    memory."""
    post = SimpleNamespace(op=SimpleNamespace(n_interior=493), spectral=None)  # 1,479 DOFs
    problem = SimpleNamespace(posterior=post)
    cfg = load_config("configs/paper_three_compartment.yaml")
    assert targets.dense_budget_bytes() == 2 * 2**30  # the tests run on a CPU
    assert targets.dense_preconditioning(problem, cfg, n_chains=245)  # 2.14 GB <= 2 GiB
    assert not targets.dense_preconditioning(problem, cfg, n_chains=256)  # 2.24 GB

    def device(stats):
        return SimpleNamespace(memory_stats=lambda: stats)

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax, "devices", lambda *a: [device({"bytes_limit": 112_583_507_968})])
    assert targets.dense_budget_bytes() == 112_583_507_968 // 16
    assert targets.dense_preconditioning(problem, cfg, n_chains=256)
    assert targets.dense_preconditioning(problem, cfg, n_chains=800)  # 7.0 GB
    assert not targets.dense_preconditioning(problem, cfg, n_chains=1024)  # 8.96 GB
    assert targets.cg_preconditioner(problem, cfg, n_chains=1024) == "block-jacobi"
    monkeypatch.setattr(jax, "devices", lambda *a: [device({"bytes_limit": 8 * 2**30})])
    assert targets.dense_budget_bytes() == 2 * 2**30  # a small device: never below the CPU's
    for stats in (None, {}, {"bytes_in_use": 0}):
        monkeypatch.setattr(jax, "devices", lambda *a, stats=stats: [device(stats)])
        assert targets.dense_budget_bytes() == 2 * 2**30
