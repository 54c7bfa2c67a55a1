"""Configuration validation: unknown keys and bad values name the key."""

import pytest

from bayesreg.config import ConfigError, load_config


def test_quickstart_config_is_valid():
    cfg = load_config("configs/quickstart.yaml")
    assert cfg.sampler.chains == 3 and cfg.sampler.rhat_threshold == 1.2
    assert cfg.model.elastic == "tissue"
    # the main job: NUTS on the 32-point quadrature with the 1 mm barrier; the paper's
    # random walk stays in configs/paper_*.yaml
    assert cfg.sampler.kind == "nuts" and cfg.sampler.thinning == 1 and cfg.sampler.use_condensed
    assert cfg.model.quadrature_level == 1 and cfg.model.skull_barrier_mm == 1.0
    # the calibrated model (the exact normaliser), mu_GM fixed to pin the scale
    assert cfg.model.prior_normaliser == "exact" and cfg.model.fixed is not None
    paper = load_config("configs/paper_three_compartment.yaml")
    assert paper.sampler.kind == "rwmh" and paper.model.quadrature_level == 0
    assert paper.model.prior_normaliser == "paper"  # the reproduction keeps Eq. 12 as published


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
    cfg = load_config("configs/quickstart.yaml", overrides=["sampler.max_draws=700", "model.t_r=2.5"])
    assert cfg.sampler.max_draws == 700 and cfg.model.t_r == 2.5
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
    assert nuts.model.model_copy(update={"skull_barrier_mm": 0.0, "quadrature_level": 0,
                                         "prior_normaliser": "paper"}) == base.model
    assert nuts.model.prior_normaliser == "exact" and base.model.prior_normaliser == "paper"
    assert base.model.skull_barrier_mm == 0.0 and nuts.sampler.joint is None
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


def _error(overrides, config="configs/quickstart.yaml"):
    with pytest.raises(ConfigError) as err:
        load_config(config, overrides=overrides)
    return str(err.value)


@pytest.mark.parametrize("item, key", [
    ("model.t_s=.inf", r"model\.t_s"), ("model.t_r=.inf", r"model\.t_r"),
    ("model.prior_lam.r2=.inf", r"model\.prior_lam\.r2"), ("model.t_s=.nan", r"model\.t_s"),
    ("model.fixed.value=1e400", r"model\.fixed\.value"),  # a YAML string, inf as a float
    ("model.fixed.value=1.0e+400", r"model\.fixed\.value"),
])
def test_infinite_values_are_errors(item, key):
    with pytest.raises(ConfigError, match=key + ": Input should be a finite number"):
        load_config("configs/quickstart.yaml", overrides=[item])


def test_initial_parameters_lie_inside_their_prior_support():
    """The start of every free parameter lies strictly inside its prior's support (the
    posterior refuses it only after meshing); a fixed parameter is not checked."""
    msg = _error(["model.initial_lam.gm=500"])
    assert ("model.initial_lam.gm (500) must lie strictly inside the support (0, 100) of "
            "model.prior_lam") in msg
    assert "support (2, 100)" in _error(["model.prior_lam.r1=2"])  # initial_lam.csf = 1
    # per-tissue priors: each tissue against its own
    tissue = "model.prior_lam={csf: {r2: 10}, gm: {r2: 100}, wm: {r2: 3}}"
    assert "model.initial_lam.wm (5) must lie strictly inside the support (0, 3) of model.prior_lam.wm" \
        in _error([tissue])
    load_config("configs/quickstart.yaml", overrides=[tissue, "model.initial_lam.wm=2"])
    # mu_GM is fixed in the quickstart: its initial value is unused
    load_config("configs/quickstart.yaml", overrides=["model.initial_mu.gm=500"])
    assert "model.initial_mu.gm" in _error(["model.initial_mu.gm=500", "model.fixed=null"])
    # uniform: the start is a volume-weighted mean of the tissues' values, so each must be inside
    msg = _error(["model.initial_lam.csf=5000"], "configs/paper_uniform.yaml")
    assert "model.initial_lam.csf" in msg and "volume-weighted mean" in msg
    load_config("configs/paper_uniform.yaml", overrides=["model.initial_mu.csf=500"])  # mu fixed


def test_seed_is_a_32_bit_unsigned_integer():
    assert load_config(None, overrides=[f"seed={2**32 - 1}"]).seed == 2**32 - 1
    with pytest.raises(ConfigError, match=r"seed: Input should be greater than or equal to 0"):
        load_config(None, overrides=["seed=-1"])
    with pytest.raises(ConfigError, match=r"seed: Input should be less than 4294967296"):
        load_config(None, overrides=[f"seed={2**32}"])


def test_bad_prior_gives_the_errors_of_its_own_form_only():
    """A union of a Beta prior and per-tissue priors: only the form given is reported."""
    assert _error(["model.prior_lam={r1: 100, r2: 10}"]).splitlines()[1:] == [
        "  model.prior_lam: r2 (10.0) must exceed r1 (100.0)"]
    assert _error(["model.prior_lam={csf: {r2: 10}, gm: {r1: 5, r2: 1}, wm: {r2: 3}}"]).splitlines()[1:] == [
        "  model.prior_lam.gm: r2 (1.0) must exceed r1 (5.0)"]
    assert _error(["model.prior_mu={r2: 10, foo: 1}"]).splitlines()[1:] == [
        "  model.prior_mu.foo: unknown key"]
    assert "model.prior_mu: Input should be a prior" in _error(["model.prior_mu=5"])


@pytest.mark.parametrize("item, key", [
    ("data.fixed=f.nii.gz", "data.fixed"), ("data.labels=l.nii.gz", "data.labels"),
    ("data.label_coding={csf: 1, gm: 2, wm: 3}", "data.label_coding"),
    ("data.moving=m.nii.gz", "data.moving"),
])
def test_data_keys_of_nifti_are_errors_with_the_template(item, key):
    assert f"{key} is only used with data.source: nifti" in _error([item])


def test_moving_image_is_an_error_with_a_synthetic_case(tmp_path):
    nifti = ["data.source=nifti", "data.fixed=f.nii.gz", "data.labels=l.nii.gz",
             "data.label_coding={csf: 1, gm: 2, wm: 3}"]
    load_config(None, overrides=nifti)  # synthetic m from the user's f
    msg = _error(nifti + ["data.moving=m.nii.gz"], None)
    assert "data.moving is not used with synthetic.enabled: true" in msg
    load_config(None, overrides=nifti + ["data.moving=m.nii.gz", "synthetic.enabled=false",
                                          "init.start=registration"])


def test_draw_counts_are_consistent():
    """Sampling runs whole chunks until max_draws: min_draws and chunk_draws may not exceed it."""
    assert ("sampler.min_draws (2000) must not exceed sampler.max_draws (1000)"
            in _error(["sampler.max_draws=1000", "sampler.min_draws=2000"]))
    assert ("sampler.chunk_draws (1500) must not exceed sampler.max_draws (1000)"
            in _error(["sampler.max_draws=1000", "sampler.chunk_draws=1500"]))
    cfg = load_config("configs/quickstart.yaml", overrides=[
        "sampler.max_draws=1000", "sampler.min_draws=1000", "sampler.chunk_draws=1000"])
    assert cfg.sampler.min_draws == cfg.sampler.chunk_draws == cfg.sampler.max_draws == 1000


def test_joint_trajectories_need_a_gradient_kernel_and_exclude_collapsed_moves():
    """``sampler.joint`` is left unset (the pipeline decides: true but with collapsed moves or
    the per-element model under the exact normaliser) and refused with the random walk or
    beside collapsed moves."""
    assert load_config("configs/quickstart.yaml").sampler.joint is None
    assert "sampler.joint needs a gradient kernel" in _error(["sampler.kind=rwmh", "sampler.joint=true"])
    assert "sampler.collapsed_moves needs sampler.joint: false" in _error(
        ["sampler.joint=true", "sampler.collapsed_moves=1"])


def test_booleans_are_not_numbers():
    """YAML reads yes/no/true/false as booleans: an integer or float key refuses them."""
    assert "sampler.chains: Input should be a valid integer" in _error(["sampler.chains=true"])
    assert "sampler.thinning: Input should be a valid integer" in _error(["sampler.thinning=yes"])
    assert "model.t_s: Input should be a valid number, not a boolean" in _error(["model.t_s=on"])
    cfg = load_config("configs/quickstart.yaml", overrides=["sampler.chains=4", "model.t_s=1e-3"])
    assert cfg.sampler.chains == 4 and cfg.model.t_s == 1e-3  # '1e-3' is a YAML string


def test_duplicate_yaml_keys_are_errors(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("sampler:\n  chains: 3\n  kind: nuts\n  chains: 4\n")
    with pytest.raises(ConfigError, match=r"duplicate key sampler\.chains \(lines 2 and 4\)"):
        load_config(p)
    p.write_text("model: {t_s: 0.1}\nseed: 1\nmodel: {t_r: 2.0}\n")
    with pytest.raises(ConfigError, match=r"duplicate key model \(lines 1 and 3\)"):
        load_config(p)
    with pytest.raises(ConfigError, match=r"duplicate key model\.prior_lam\.r2"):
        load_config(None, overrides=["model.prior_lam={r2: 10, r2: 20}"])
    # a merge key's values may be overridden
    p.write_text("model:\n  prior_lam: &p {r1: 0.0, r2: 100.0}\n  prior_mu: {<<: *p, r2: 10.0}\n")
    assert load_config(p).model.prior_mu.r2 == 10.0


def test_empty_config_file_is_an_error(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("")
    with pytest.raises(ConfigError, match=f"config file {p} is empty"):
        load_config(p)
    p.write_text("# only a comment\n")
    with pytest.raises(ConfigError, match="is empty"):
        load_config(p)
    (tmp_path / "child.yaml").write_text("extends: c.yaml\nseed: 2\n")
    with pytest.raises(ConfigError, match=r"c\.yaml is empty"):
        load_config(tmp_path / "child.yaml")


def test_override_config_follows_the_kind_and_leaves_the_original_alone():
    from bayesreg.config import override_config

    cfg = load_config(overrides=["sampler.kind=nuts"])
    assert (cfg.sampler.thinning, cfg.sampler.warmup_steps) == (1, 500)
    rw = override_config(cfg, ["sampler.kind=rwmh"], output__dir="runs/x")
    # the per-kind defaults follow the new kind, as load_config with the same overrides gives
    assert rw.model_dump() == load_config(overrides=["sampler.kind=rwmh", "output.dir=runs/x"]).model_dump()
    assert (rw.sampler.thinning, rw.sampler.warmup_steps) == (10, 2000)
    assert cfg.sampler.kind == "nuts" and str(cfg.output.dir) != "runs/x"  # unchanged
    given = override_config(load_config(overrides=["sampler.thinning=3"]), ["sampler.kind=nuts"])
    assert given.sampler.thinning == 3  # a value given is kept
    with pytest.raises(ConfigError, match="sampler.chainz: unknown key"):
        override_config(cfg, ["sampler.chainz=3"])
    with pytest.raises(ConfigError, match="a list of 'key=value' strings"):
        override_config(cfg, "seed=3")


def test_a_partial_tissue_mapping_keeps_the_defaults_of_the_rest(tmp_path):
    cfg = load_config(overrides=["model.initial_lam.gm=7", "model.prior_lam.a=2", "synthetic.mu.wm=3"])
    assert (cfg.model.initial_lam.csf, cfg.model.initial_lam.gm, cfg.model.initial_lam.wm) == (1.0, 7.0, 5.0)
    assert (cfg.model.prior_lam.a, cfg.model.prior_lam.r2) == (2.0, 100.0)
    assert (cfg.synthetic.mu.gm, cfg.synthetic.mu.wm) == (1.0, 3.0)
    path = tmp_path / "c.yaml"
    path.write_text("model:\n  initial_mu: {gm: 2}\n")
    assert load_config(path).model.initial_mu.model_dump() == {"csf": 1.0, "gm": 2.0, "wm": 1.0}
    with pytest.raises(ConfigError, match=r"model.initial_lam.gm: Input should be greater than 0"):
        load_config(overrides=["model.initial_lam.gm=-1"])


def test_union_errors_read_as_one_line_per_key():
    """``Int | list[Int]`` (a label code or a list of codes): pydantic reports one error per
    union member, tagged ``int`` and ``list[int]``; the message gives one line per key."""
    nifti = ["data.source=nifti", "data.fixed=f.nii.gz", "data.labels=l.nii.gz"]
    lines = _error(nifti + ["data.label_coding={csf: abc, gm: 2, wm: 3}"], None).splitlines()
    assert lines[1:] == ["  data.label_coding.csf: Input should be a valid integer, or a valid list"]
    lines = _error(nifti + ["data.label_coding={csf: [1, x], gm: 2, wm: 3}"], None).splitlines()
    assert "  data.label_coding.csf.1: Input should be a valid integer" in lines
    assert not any("list[int]" in line for line in lines)


def test_mesh_file_is_read_from_the_configs_folder_and_excludes_a_node_target(tmp_path):
    (tmp_path / "sub").mkdir()
    p = tmp_path / "sub" / "c.yaml"
    p.write_text("extends: ../base.yaml\nmesh:\n  file: meshes/brain.vtu\n")
    (tmp_path / "base.yaml").write_text("name: base\n")
    cfg = load_config(p)
    assert cfg.mesh.file == (tmp_path / "sub" / "meshes" / "brain.vtu").resolve()
    over = load_config(p, overrides=["mesh.file=other.msh"])  # --set: the config's folder too
    assert over.mesh.file == (tmp_path / "sub" / "other.msh").resolve()
    assert load_config(p, overrides=["mesh.file=/abs/m.vtu"]).mesh.file.as_posix() == "/abs/m.vtu"
    with pytest.raises(ConfigError, match="mesh.file and mesh.target_nodes exclude each other"):
        load_config(p, overrides=["mesh.target_nodes=800"])


def test_brainweb_source_keys(tmp_path):
    cfg = load_config(None, overrides=["data.source=brainweb", "data.subject=5"])
    assert cfg.data.resolution_mm == 1.0 and cfg.data.subject == 5  # the paper's 1 mm by default
    cfg = load_config(None, overrides=["data.source=brainweb", "data.subject=5", "data.resolution_mm=2"])
    assert cfg.data.resolution_mm == 2.0
    assert "data.source 'brainweb' needs data.subject" in _error(["data.source=brainweb"], None)
    assert "multiple of 0.5 mm" in _error(["data.source=brainweb", "data.subject=5",
                                           "data.resolution_mm=1.2"], None)
    assert "data.subject is only used with data.source: brainweb" in _error(["data.subject=5"])
    assert "data.noise_percent is only used with data.source: brainweb" in _error(["data.noise_percent=3"])
    # a path (relative to the config's folder) instead of a subject number
    (tmp_path / "c.yaml").write_text("data: {source: brainweb, subject: models/s.mnc.gz, brainweb_dir: bw}\n")
    cfg = load_config(tmp_path / "c.yaml")
    assert cfg.data.subject == (tmp_path / "models/s.mnc.gz").resolve()
    assert cfg.data.brainweb_dir == (tmp_path / "bw").resolve()


def test_truths_the_model_did_not_make_refuse_the_fe_truths_keys(tmp_path):
    """``bump`` and ``field`` have no Lamé parameters: the quickstart's ``lam``/``mu`` are
    errors until removed (``null``); ``field`` needs its file (read from the config's
    folder) and only it; a resolved config (every key written) validates again."""
    from bayesreg.config import Config

    bump = ["synthetic.truth=bump"]
    msg = _error(bump)
    assert "synthetic.lam, synthetic.mu are not used by synthetic.truth: bump" in msg
    cfg = load_config("configs/quickstart.yaml", overrides=bump + ["synthetic.lam=null", "synthetic.mu=null"])
    assert cfg.synthetic.truth == "bump"
    assert Config.model_validate(cfg.model_dump(mode="json")).synthetic.truth == "bump"
    assert "synthetic.outside is not used" in _error(bump + ["synthetic.lam=null", "synthetic.mu=null",
                                                            "synthetic.outside=background"])
    assert "synthetic.truth: field and synthetic.field go together" in _error(
        ["synthetic.truth=field", "synthetic.lam=null", "synthetic.mu=null"])
    assert "go together" in _error(["synthetic.field=u.nii.gz"])
    shipped = load_config("configs/mismatch_bump.yaml")  # the quickstart with a bump
    assert shipped.synthetic.truth == "bump" and shipped.init.start == "registration"
    assert shipped.model.interior == "solve" and shipped.model.fixed is None
    # the FE interior with a model discrepancy, sampled as mismatch_discrepancy.yaml samples it
    assert shipped.model.discrepancy == "interior" and shipped.synthetic.discrepancy_mm == 0.0
    assert not shipped.sampler.joint and shipped.sampler.collapsed_moves > 0
    assert shipped.sampler.carry == "displacement" and not shipped.synthetic.solenoidal
    p = tmp_path / "c.yaml"
    p.write_text("synthetic:\n  truth: field\n  field: fields/u.nii.gz\n")
    assert load_config(p).synthetic.field == (tmp_path / "fields" / "u.nii.gz").resolve()
    assert "synthetic.shift_mm is not used" in _error(
        ["synthetic.truth=field", "synthetic.field=u.nii.gz", "synthetic.shift_mm=3"], None)


def test_sampling_the_interior_needs_the_exact_normaliser():
    assert "model.interior: sample needs model.prior_normaliser: exact" in _error(
        ["model.interior=sample", "model.prior_normaliser=paper"])
    cfg = load_config("configs/quickstart.yaml", overrides=[
        "model.interior=sample", "model.prior_normaliser=exact", "model.fixed=null"])
    assert cfg.model.interior == "sample"


def test_a_model_discrepancy_needs_the_solved_interior_and_a_gradient_sampler():
    cfg = load_config("configs/quickstart.yaml", overrides=["model.discrepancy=interior"])
    assert cfg.model.discrepancy == "interior" and cfg.model.discrepancy_prior.floor_mm == 0.05
    assert load_config("configs/quickstart.yaml").model.discrepancy == "none"
    assert "needs model.interior: solve" in _error(
        ["model.discrepancy=interior", "model.interior=sample", "model.fixed=null"])
    assert "needs a gradient sampler" in _error(["model.discrepancy=interior", "sampler.kind=rwmh"])
    # collapsed moves carry [u_b, d] (their Gaussian is of the nodal displacement)
    cfg = load_config("configs/quickstart.yaml", overrides=[
        "model.discrepancy=interior", "sampler.collapsed_moves=2", "sampler.joint=false"])
    assert cfg.sampler.collapsed_moves == 2 and cfg.collapsed_carry == "displacement"
    # carrying the displacement needs no Laplace curvature; the Gaussian does
    cfg = load_config("configs/quickstart.yaml", overrides=[
        "model.discrepancy=interior", "sampler.collapsed_moves=2", "sampler.joint=false",
        "sampler.proposal=isotropic"])
    assert cfg.collapsed_carry == "displacement"
    assert "carry: conditional needs sampler.proposal: laplace" in _error(
        ["model.discrepancy=interior", "sampler.collapsed_moves=2", "sampler.joint=false",
         "sampler.proposal=isotropic", "sampler.carry=conditional"])
    assert load_config("configs/quickstart.yaml", overrides=[
        "sampler.collapsed_moves=2", "sampler.joint=false"]).collapsed_carry == "conditional"
    assert "carry: displacement needs a model discrepancy" in _error(
        ["sampler.collapsed_moves=2", "sampler.joint=false", "sampler.carry=displacement"])
    assert "carry: conditional needs sampler.proposal: laplace" in _error(
        ["sampler.collapsed_moves=2", "sampler.joint=false", "sampler.proposal=isotropic"])
    assert "floor_mm" in _error(["model.discrepancy=interior", "model.discrepancy_prior.floor_mm=0"])
    # the low-rank discrepancy: the same rules, and at least one mode
    cfg = load_config("configs/quickstart.yaml", overrides=["model.discrepancy=modes"])
    assert cfg.model.discrepancy == "modes" and cfg.model.discrepancy_prior.modes == 64
    assert "model.discrepancy: modes needs a gradient sampler" in _error(
        ["model.discrepancy=modes", "sampler.kind=rwmh"])
    assert "modes" in _error(["model.discrepancy=modes", "model.discrepancy_prior.modes=0"])
