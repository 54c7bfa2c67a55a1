"""Configuration validation: unknown keys and bad values name the key."""

import pytest

from bayesreg.config import ConfigError, load_config


def test_quickstart_config_is_valid():
    cfg = load_config("configs/quickstart.yaml")
    assert cfg.sampler.chains == 3 and cfg.sampler.rhat_threshold == 1.2
    assert cfg.model.elastic == "tissue"
    # the main job: NUTS on the 32-point quadrature with the 1 mm barrier (converges in
    # minutes); the paper's random walk stays in configs/paper_*.yaml
    assert cfg.sampler.kind == "nuts" and cfg.sampler.thinning == 1 and cfg.sampler.use_condensed
    assert cfg.model.quadrature_level == 1 and cfg.model.skull_barrier_mm == 1.0
    assert cfg.model.prior_normaliser == "paper" and cfg.model.fixed is not None
    paper = load_config("configs/paper_three_compartment.yaml")
    assert paper.sampler.kind == "rwmh" and paper.model.quadrature_level == 0


def test_unknown_key_is_named(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("sampler:\n  chainz: 3\n")
    with pytest.raises(ConfigError, match=r"sampler\.chainz: unknown key"):
        load_config(p)


def test_bad_value_is_named(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("model:\n  t_s: -1\n")
    with pytest.raises(ConfigError, match=r"model\.t_s"):
        load_config(p)


def test_overrides_are_validated():
    cfg = load_config("configs/quickstart.yaml", overrides=["sampler.max_draws=7", "model.t_r=2.5"])
    assert cfg.sampler.max_draws == 7 and cfg.model.t_r == 2.5
    with pytest.raises(ConfigError, match=r"sampler\.chains"):
        load_config("configs/quickstart.yaml", overrides=["sampler.chains=1"])
    with pytest.raises(ConfigError, match="key=value"):
        load_config("configs/quickstart.yaml", overrides=["sampler.chains"])


def test_fixed_group_must_exist(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("model:\n  elastic: uniform\n  fixed: {param: mu, group: gm, value: 1}\n")
    with pytest.raises(ConfigError, match="not a group"):
        load_config(p)


def test_nifti_source_needs_paths(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("data:\n  source: nifti\n")
    with pytest.raises(ConfigError, match="data.fixed"):
        load_config(p)


def test_beta_prior_range(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("model:\n  prior_lam: {r1: 5, r2: 1}\n")
    with pytest.raises(ConfigError, match="prior_lam"):
        load_config(p)


def test_extends_merges_the_base_config(tmp_path):
    """A child config gives only what differs: mappings merge, null replaces."""
    (tmp_path / "base.yaml").write_text(
        "name: base\nmodel:\n  t_r: 5.0\n  fixed: {param: mu, group: gm, value: 1.0}\nsampler:\n  chains: 4\n")
    (tmp_path / "child.yaml").write_text("extends: base.yaml\nmodel:\n  fixed: null\nsampler:\n  kind: nuts\n")
    cfg = load_config(tmp_path / "child.yaml")
    assert cfg.name == "base" and cfg.model.t_r == 5.0 and cfg.model.fixed is None
    assert cfg.sampler.kind == "nuts" and cfg.sampler.chains == 4
    (tmp_path / "a.yaml").write_text("extends: b.yaml\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "a.yaml")
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        (tmp_path / "c.yaml").write_text("extends: missing.yaml\n")
        load_config(tmp_path / "c.yaml")


@pytest.mark.parametrize("model", ["uniform", "three_compartment"])
def test_paper_configs_gradient_variants_differ_only_in_the_sampler(model):
    base = load_config(f"configs/paper_{model}.yaml")
    nuts = load_config(f"configs/paper_{model}_nuts.yaml")
    assert base.sampler.kind == "rwmh" and nuts.sampler.kind == "nuts"
    assert nuts.synthetic == base.synthetic and nuts.mesh == base.mesh
    assert nuts.model.model_copy(update={"skull_barrier_mm": 0.0, "quadrature_level": 0}) == base.model
    assert nuts.model.prior_normaliser == "paper" and base.model.skull_barrier_mm == 0.0
    assert nuts.model.skull_barrier_mm == 1.0
    assert base.model.quadrature_level == 0 and nuts.model.quadrature_level == 1


def test_sampler_defaults_follow_the_kernel():
    """New configs default to NUTS (thinning 1, 500 warm-up steps) and the exact normaliser;
    a random walk gets thinning 10 and 2000 warm-up steps unless given."""
    cfg = load_config(None)
    assert cfg.sampler.kind == "nuts" and cfg.sampler.thinning == 1 and cfg.sampler.warmup_steps == 500
    assert cfg.model.prior_normaliser == "exact" and cfg.sampler.use_condensed
    assert cfg.model.skull_barrier_mm == 1.0 and cfg.model.quadrature_level == 1
    rw = load_config(None, overrides=["sampler.kind=rwmh"])
    assert rw.sampler.thinning == 10 and rw.sampler.warmup_steps == 2000 and not rw.sampler.use_condensed
    given = load_config(None, overrides=["sampler.kind=rwmh", "sampler.thinning=3"])
    assert given.sampler.thinning == 3


def test_run_written_before_the_barrier_resumes_without_it(tmp_path):
    """A checkpointed config without ``model.skull_barrier_mm`` and ``quadrature_level`` (a run
    from before the keys existed) resumes with the hard constraint alone and the 4-point rule,
    not the later defaults (1 mm, level 1)."""
    import json

    from bayesreg.checkpoint import Checkpoint

    cfg = load_config("configs/quickstart.yaml")
    raw = cfg.model_dump(mode="json")
    del raw["model"]["skull_barrier_mm"], raw["model"]["quadrature_level"]
    (tmp_path / "checkpoint").mkdir()
    (tmp_path / "checkpoint" / "config.json").write_text(json.dumps(raw))
    resumed = Checkpoint(tmp_path).load_config().model
    assert resumed.skull_barrier_mm == 0.0 and resumed.quadrature_level == 0
    assert load_config(None).model.skull_barrier_mm == 1.0


def test_preconditioner_choice_follows_size_and_memory():
    """``solver.preconditioner: auto`` takes the spectral preconditioner where the posterior
    has one (one parameter group), else the dense one where its inverses fit (``3 n_i <=
    4096`` DOFs, at most 2 GiB for all chains), else block Jacobi; a bad value names the key."""
    from types import SimpleNamespace

    from bayesreg.pipeline import cg_preconditioner, dense_preconditioning

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


def test_paper_configs_mesh_to_the_papers_node_count():
    for model in ("uniform", "three_compartment"):
        cfg = load_config(f"configs/paper_{model}.yaml")
        assert cfg.mesh.target_nodes == 801 and cfg.mesh.target_tolerance == 0.05
    assert load_config("configs/quickstart.yaml").mesh.target_nodes is None
    for bad, key in (("mesh.target_nodes=10", r"mesh\.target_nodes"),
                     ("mesh.target_tolerance=1.5", r"mesh\.target_tolerance"),
                     ("mesh.max_attempts=0", r"mesh\.max_attempts")):
        with pytest.raises(ConfigError, match=key):
            load_config("configs/quickstart.yaml", overrides=[bad])
