"""Reading a configuration: YAML files, ``extends``, ``--set`` overrides, readable errors.

Load with :func:`load_config`; override single values with ``--set key.sub=value``
(:func:`apply_overrides`, values parsed as YAML).  Also errors, before any meshing: a key
given twice in one mapping, an empty file, a cycle of ``extends``.
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml
from pydantic import ValidationError

from bayesreg.config.models import PRIOR_TAGS, Config, ConfigError

__all__ = ["load_config", "override_config", "apply_overrides", "format_errors", "load_model_file"]


#: pydantic's tags of the members of a plain union (``Int | list[Int]``) in an error's location
_UNION_TAG = re.compile(r"^(int|float|str|bool|list\[.*\]|dict\[.*\])$")


def format_errors(err: ValidationError, source: str) -> str:
    entries: list[tuple[str, str]] = []
    for e in err.errors():
        loc = e["loc"]
        # drop the branch tag of the prior union (model.prior_lam.beta.r2 -> model.prior_lam.r2)
        loc = [p for i, p in enumerate(loc)
               if not (p in PRIOR_TAGS and i and loc[i - 1] in ("prior_lam", "prior_mu"))]
        tags = [isinstance(p, str) and bool(_UNION_TAG.match(p)) for p in loc]
        union = any(tags)
        key = ".".join(str(p) for p, t in zip(loc, tags) if not t) or "(top level)"
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        if e["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
        if union and entries and entries[-1][0] == key:  # one line per key: "a valid integer, or ..."
            entries[-1] = (key, f"{entries[-1][1]}, or {msg.removeprefix('Input should be ')}")
        else:
            entries.append((key, msg))
    return "\n".join([f"invalid configuration {source}:"] + [f"  {k}: {m}" for k, m in entries])


def _set_path(d: dict, dotted: str, value):
    keys = dotted.split(".")
    cur = d
    for k in keys[:-1]:
        cur = cur.setdefault(k, {})
        if not isinstance(cur, dict):
            raise ConfigError(f"--set {dotted}: '{k}' is not a section")
    cur[keys[-1]] = value


class _DuplicateKey(Exception):
    def __init__(self, key: str, first: int, again: int):
        super().__init__(key, first, again)
        self.key, self.first, self.again = key, first, again


def _check_duplicate_keys(node, path: tuple, seen_nodes: set) -> None:
    """Raise :class:`_DuplicateKey` for a key given twice in one mapping (YAML would keep the
    last silently).  Keys brought in by a merge (``<<: *anchor``) may be overridden."""
    if id(node) in seen_nodes:
        return
    seen_nodes.add(id(node))
    if isinstance(node, yaml.MappingNode):
        lines: dict = {}
        for k, v in node.value:
            if k.tag == "tag:yaml.org,2002:merge":
                _check_duplicate_keys(v, path, seen_nodes)
                continue
            name = k.value if isinstance(k, yaml.ScalarNode) else None
            if name is not None:
                if name in lines:
                    raise _DuplicateKey(".".join(path + (name,)), lines[name], k.start_mark.line + 1)
                lines[name] = k.start_mark.line + 1
            _check_duplicate_keys(v, path + (str(name),), seen_nodes)
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            _check_duplicate_keys(v, path + (str(i),), seen_nodes)


def _load_yaml(text: str):
    """``yaml.safe_load`` that refuses a key given twice in one mapping (:class:`_DuplicateKey`)."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_duplicate_keys(node, (), set())
        return loader.construct_document(node)
    finally:
        loader.dispose()


def load_model_file(path, model, *, what: str, overrides: list[str] | None = None):
    """A YAML file (``None``: an empty mapping) with ``key=value`` overrides, validated as the
    pydantic ``model``: the reading shared by the sweep and calibration files (a run's
    config, with ``extends``, is :func:`load_config`'s).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist (the message names ``what``).
    ConfigError
        Bad YAML, an unknown key or a bad value (the message names it).
    """
    raw, source = {}, "defaults"
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{what} not found: {path}")
        try:
            raw = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {exc}") from None
        source = str(path)
    raw = apply_overrides(raw, overrides)
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_errors(exc, source)) from None


def apply_overrides(raw: dict, overrides: list[str] | None) -> dict:
    """Apply ``key.sub=value`` strings to a raw config dict (values parsed as YAML).

    Raises
    ------
    ConfigError
        If ``overrides`` is a string rather than a list, or an item is not ``key=value``
        with a dotted key and a valid YAML value (the item is shown).
    """
    if isinstance(overrides, str):
        raise ConfigError(f"overrides must be a list of 'key=value' strings, got the string {overrides!r}")
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got '{item}'")
        key, val = item.split("=", 1)
        parts = key.strip().split(".")
        if not all(re.fullmatch(r"[A-Za-z_]\w*", k) for k in parts):
            raise ConfigError(f"--set {item!r}: the key must be dotted names, e.g. "
                              f"sampler.max_draws=500; got {key.strip()!r}")
        try:
            value = _load_yaml(val)
        except _DuplicateKey as exc:
            raise ConfigError(f"--set {item}: duplicate key {key.strip()}.{exc.key}") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"--set {item}: not a valid YAML value: {exc}") from None
        _set_path(raw, key.strip(), value)
    return raw


def override_config(cfg: Config, overrides: list[str] | None = None, **values) -> Config:
    """A new config: ``cfg`` with ``key.sub=value`` overrides and dotted ``values`` applied.

    Re-validated from the keys ``cfg`` was given, so defaults that follow other keys follow
    the overrides (the sampler's ``thinning`` and ``warmup_steps`` follow ``sampler.kind``,
    as in :func:`load_config`).  ``cfg`` is not changed.

    Parameters
    ----------
    cfg : Config
    overrides : list of str, optional
        As ``--set`` (values parsed as YAML).
    **values
        ``section__key=value`` pairs set as Python values (e.g. ``output__dir=path``).

    Raises
    ------
    ConfigError
        On unknown keys or bad values (the message names each key).
    """
    raw = apply_overrides(cfg.model_dump(mode="json", exclude_unset=True), overrides)
    for key, value in values.items():
        _set_path(raw, key.replace("__", "."), value)
    try:
        return Config.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_errors(exc, "(overrides)")) from None


def _read_raw(path: Path, chain: tuple) -> dict:
    """The raw mapping of one YAML file, with ``extends: OTHER.yaml`` (relative to the file's
    folder) merged under it: mappings merge key by key, any other value (``null`` included)
    replaces the base's."""
    if not path.exists():
        raise FileNotFoundError(f"config not found: {path}")
    try:
        raw = _load_yaml(path.read_text())
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}: duplicate key {exc.key} (lines {exc.first} and {exc.again}): "
                          "give each key once") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if raw is None:  # not a run of every default: most likely a file not written yet
        raise ConfigError(f"config file {path} is empty (for a run of the defaults give none)")
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: the top level must be a mapping")
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if not isinstance(base, str):
        raise ConfigError(f"{path}: extends must be the file name of another config, got {base!r}")
    base_path = (path.parent / base).resolve()
    if base_path in chain or base_path == path.resolve():
        raise ConfigError(f"{path}: extends {base} makes a cycle")
    return _merge(_read_raw(base_path, chain + (path.resolve(),)), raw)


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_config(path=None, *, overrides: list[str] | None = None, base_dir=None) -> Config:
    """Read, override and validate a YAML config.

    Relative data paths (and ``mesh.file``) are resolved against the config file's folder.  A config may start
    from another with ``extends: OTHER.yaml`` (relative to its folder) and give only what
    differs (mappings merge key by key; ``null`` replaces).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ConfigError
        On YAML syntax errors, unknown keys or bad values (the message names each key).
    """
    raw: dict = {}
    source = "(defaults)"
    if path is not None:
        path = Path(path)
        raw = _read_raw(path, ())
        source = str(path)
        base_dir = base_dir or path.parent
    raw = apply_overrides(raw, overrides)
    try:
        cfg = Config.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(format_errors(exc, source)) from None
    if base_dir is not None:
        for part, k in (("data", "fixed"), ("data", "moving"), ("data", "labels"), ("data", "subject"),
                        ("data", "brainweb_dir"), ("mesh", "file"), ("synthetic", "field")):
            p = getattr(getattr(cfg, part), k)
            if isinstance(p, Path) and not p.is_absolute():
                setattr(getattr(cfg, part), k, (Path(base_dir) / p).resolve())
    return cfg
