"""Configuration validation: unknown keys and bad values name the key."""

import pytest

from bayesreg.config import ConfigError, load_config


def test_quickstart_config_is_valid():
    cfg = load_config("configs/quickstart.yaml")
    assert cfg.sampler.chains == 3 and cfg.sampler.rhat_threshold == 1.2
    assert cfg.model.elastic == "tissue"


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
