"""Run configuration: pydantic models (:mod:`bayesreg.config.models`) read from YAML
(:mod:`bayesreg.config.loading`).

``configs/quickstart.yaml`` is a commented example of the common keys; the documentation's
configuration reference lists every key, generated from the models.
"""

from bayesreg.config.loading import apply_overrides, format_errors, load_config, override_config
from bayesreg.config.models import Config, ConfigError

__all__ = ["Config", "ConfigError", "load_config", "override_config", "apply_overrides",
           "format_errors"]
