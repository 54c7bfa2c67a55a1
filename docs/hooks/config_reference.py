"""MkDocs hook: the configuration reference, generated from the pydantic models.

A page holding the marker ``<!-- config-reference -->`` gets, in its place, one table per
section of :class:`bayesreg.config.Config` (``data``, ``mesh``, ...): every key with its
type, default, allowed values or bounds and the ``description`` of its field, followed by
a table for each nested value type (a Beta prior, per-tissue values, ...).  The models in
``bayesreg/config/models.py`` are the one place a key is documented; this hook only
renders them, so the reference cannot drift from the code.

Registered under ``hooks:`` in ``mkdocs.yml``.
"""

from __future__ import annotations

import html
import sys
import types
import typing
from pathlib import Path

MARKER = "<!-- config-reference -->"


def _models():
    try:
        from bayesreg.config import models
    except ImportError:  # a checkout that is not installed: the sources beside mkdocs.yml
        sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
        from bayesreg.config import models
    return models


def _is_model(tp) -> bool:
    from pydantic import BaseModel

    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _strip(tp):
    """The type without its ``Annotated`` metadata, and that metadata."""
    meta = []
    while typing.get_origin(tp) is typing.Annotated:
        meta += list(tp.__metadata__)
        tp = tp.__origin__
    return tp, meta


def _union_args(tp):
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return list(typing.get_args(tp))
    return None


def _anchor(cls) -> str:
    return "type-" + cls.__name__.lower()


def _type(tp, anchors: dict) -> str:
    tp, _ = _strip(tp)
    args = _union_args(tp)
    if args is not None:
        return " or ".join(_type(a, anchors) for a in args)
    if tp is type(None):
        return "null"
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        kinds = {type(v).__name__ for v in typing.get_args(tp)}
        return "string" if kinds == {"str"} else " or ".join(sorted(kinds))
    if origin in (list, tuple):
        return f"list of {_type(typing.get_args(tp)[0], anchors)}"
    if origin is dict:
        k, v = typing.get_args(tp)
        return f"mapping of {_type(k, anchors)} to {_type(v, anchors)}"
    if _is_model(tp):
        return f"[{tp.__name__}](#{anchors[tp]})" if tp in anchors else tp.__name__
    return {bool: "bool", int: "int", float: "float", str: "string", Path: "path"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def _value(v) -> str:
    """A value as written in YAML."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if _is_model(type(v)):
        return _value(v.model_dump(mode="json"))
    return str(v)


def _default(field) -> str:
    from pydantic_core import PydanticUndefined

    if field.default_factory is not None:
        return f"`{_value(field.default_factory())}`"
    if field.default is PydanticUndefined:
        return "required"
    return f"`{_value(field.default)}`"


_BOUNDS = (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤"))


def _allowed(field) -> str:
    tp, meta = _strip(field.annotation)
    meta = list(field.metadata) + meta
    parts = []
    for arg in (_union_args(tp) or [tp]):
        arg, inner = _strip(arg)
        meta += inner
        if typing.get_origin(arg) is typing.Literal:
            parts += [f"`{_value(v)}`" for v in typing.get_args(arg)]
        elif arg is bool:
            parts += ["`true`", "`false`"]
    for attr, sign in _BOUNDS:
        for m in meta:
            bound = getattr(m, attr, None)
            if bound is not None:
                parts.append(f"{sign} {bound}")
                break
    if any(arg is type(None) for arg in (_union_args(tp) or [])):
        parts.append("`null`")
    return ", ".join(dict.fromkeys(parts))


def _text(s: str | None) -> str:
    s = html.escape(" ".join((s or "").split()), quote=False)
    return s.replace("|", "&#124;")


def _nested(tp) -> list:
    """The models inside a field's type (a union's members, a list's items)."""
    tp, _ = _strip(tp)
    if _is_model(tp):
        return [tp]
    out = []
    for arg in typing.get_args(tp):
        out += _nested(arg)
    return out


_HEAD = ["| key | type | default | allowed | description |", "|---|---|---|---|---|"]


def _row(key: str, field, anchors: dict) -> str:
    return (f"| `{key}` | {_type(field.annotation, anchors)} | {_default(field)} | "
            f"{_allowed(field)} | {_text(field.description)} |")


def _table(cls, prefix: str, anchors: dict) -> list[str]:
    return _HEAD + [_row(f"{prefix}{name}", f, anchors) for name, f in cls.model_fields.items()]


def _doc(cls) -> list[str]:
    from pydantic import BaseModel

    doc = cls.__doc__
    if not doc or doc is BaseModel.__doc__:
        return []
    return [_text(doc.strip().split("\n\n")[0]), ""]


def _compress(paths: list[str]) -> list[str]:
    """``a.x``, ``a.y``, ``a.z`` as ``a.{x,y,z}``."""
    groups: dict[tuple, list[str]] = {}
    for p in paths:
        head, _, tail = p.rpartition(".")
        if tail in ("csf", "gm", "wm"):
            groups.setdefault((head, True), []).append(tail)
        else:
            groups.setdefault((p, False), [])
    return [f"{head}.{{{','.join(tails)}}}" if grouped else head
            for (head, grouped), tails in groups.items()]


def _section(title: str, cls, prefix: str, taken: set) -> list[str]:
    # the nested value types of this section, each with every key that takes it
    users: dict[type, list[str]] = {}
    todo = [(cls, prefix)]
    while todo:
        model, pre = todo.pop(0)
        for name, field in model.model_fields.items():
            for sub in _nested(field.annotation):
                users.setdefault(sub, []).append(f"{pre}{name}")
                todo.append((sub, f"{pre}{name}."))
    anchors = {}
    for sub in users:  # one table per type and section: its links stay in the section
        anchors[sub] = _anchor(sub) if _anchor(sub) not in taken else f"{_anchor(sub)}-{title}"
        taken.add(anchors[sub])
    lines = [f"## `{title}`", ""] + _doc(cls) + _table(cls, prefix, anchors) + [""]
    for sub, paths in users.items():
        keys = ", ".join(f"`{p}`" for p in _compress(paths))
        lines += [f"### {sub.__name__}: {keys} {{ #{anchors[sub]} }}", ""] + _doc(sub)
        lines += _table(sub, "", anchors) + [""]
    return lines


def render() -> str:
    """The reference: the top-level keys, then one section per sub-model of ``Config``."""
    Config = _models().Config
    top = [(n, f) for n, f in Config.model_fields.items() if not _nested(f.annotation)]
    lines = ["## Top level", ""] + _HEAD + [_row(n, f, {}) for n, f in top] + [""]
    taken: set = set()
    for name, field in Config.model_fields.items():
        subs = _nested(field.annotation)
        if subs:
            lines += _section(name, subs[0], f"{name}.", taken)
    return "\n".join(lines)


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, render())
