"""Griffe extension: the Sphinx markup of bayesreg's numpydoc docstrings, as Markdown.

The docstrings are written for numpydoc (Sphinx): cross-references are roles
(:func:`bayesreg.run`, :class:`~bayesreg.mesh.tetmesh.Mesh`), a literal block follows ``::`` and a
few tables are reST simple tables.  mkdocstrings renders docstrings as Markdown, so this
extension rewrites, for the documentation only (the sources are not touched):

* a role into an optional cross-reference of mkdocs-autorefs: a link where the target is
  documented on the site, inline code where it is not (Python's own classes, a private
  helper), never a warning;
* a paragraph ending in ``::`` into one ending in ``:`` (the indented block after it is
  already a Markdown code block);
* a reST simple table (rows between lines of ``=``) into a fenced block, as written;
* an entry of a Parameters, Returns or Attributes section written on one line,
  ``name : type  description`` (two spaces or more before the description), into
  numpydoc's two lines, so that the type column holds the type alone.

Loaded by mkdocstrings-python (``extensions:`` in ``mkdocs.yml``).
"""

from __future__ import annotations

import html
import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|exc|obj|const):`(~?)([^`<>]+?)`")
_RULE = re.compile(r"^( *)=+( +=+)+ *$")


def _resolve(root: griffe.Object, obj: griffe.Object, target: str) -> str:
    """The full path of ``target`` seen from ``obj``: as written if it starts with the
    package's name, else the first of its enclosing class, its module and its package
    parents that holds it (the name as written if none does)."""
    target = target.strip().lstrip(".")
    absolute = target.startswith(root.name + ".") or target == root.name
    scopes = [root.parent or root] if absolute else []
    scope = obj
    while scope is not None:
        scopes.append(scope)
        scope = scope.parent
    for scope in scopes:
        try:
            found = root if target == root.name else (
                root[target.removeprefix(root.name + ".")] if absolute else scope[target])
        except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        # a name re-exported by a package is documented where it is defined
        try:
            return found.final_target.path if found.is_alias else found.path
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return f"{scope.path}.{target}"
    return target


def _roles(text: str, root: griffe.Object, obj: griffe.Object) -> str:
    def sub(m: re.Match) -> str:
        short, target = m.group(1), m.group(2).strip()
        path = _resolve(root, obj, target)
        title = target.rsplit(".", 1)[-1] if short else target
        return (f'<autoref identifier="{html.escape(path)}" optional>'
                f"<code>{html.escape(title)}</code></autoref>")

    return _ROLE.sub(sub, text)


def _plain(text: str) -> str:
    """Roles as their plain names and no reST literals: for text that is shown verbatim
    (a fenced table, the type column of a field)."""
    text = _ROLE.sub(lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), text)
    return text.replace("``", "")


def _literal_markers(text: str) -> str:
    """"text::" before an indented block as "text:" (the block is Markdown code already),
    the block's roles and literals made plain (it is shown verbatim)."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        m = re.match(r"^(\s*)(.*\S)::[ \t]*$", line)
        if not m:
            out.append(line)
            i += 1
            continue
        indent = len(m.group(1))
        out.append(f"{m.group(1)}{m.group(2)}:")
        i += 1
        while i < len(lines) and (not lines[i].strip()
                                  or len(lines[i]) - len(lines[i].lstrip()) > indent):
            out.append(_plain(lines[i]))
            i += 1
    return "\n".join(out)


def _tables(text: str) -> str:
    """Fence each reST simple table (three rules: top, below the header or first row, end)."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        if _RULE.match(lines[i]):
            rules = [i]
            j = i + 1
            while j < len(lines) and len(rules) < 3:
                if _RULE.match(lines[j]):
                    rules.append(j)
                elif not lines[j].strip() and len(rules) >= 2 and j + 1 < len(lines) \
                        and not lines[j + 1].strip():
                    break
                j += 1
            if len(rules) >= 2:
                end = rules[-1]
                block = [_plain(ln) for ln in lines[i:end + 1] if not _RULE.match(ln)]
                out += ["```text", *block, "```"]
                i = end + 1
                continue
        out.append(lines[i])
        i += 1
    return "\n".join(out)


_FIELD_SECTIONS = {"parameters", "other parameters", "returns", "yields", "receives",
                   "attributes"}
_TYPE_SECTIONS = {"raises", "warns"}
_ENTRY = re.compile(r"^(?P<name>[^\s:][^:]*?) : (?P<type>\S.*)$")
_COMPACT = re.compile(r"^(?P<name>[^\s:][^:]*?) : (?P<type>\S.*?)\s{2,}(?P<desc>\S.*)$")


def _fields(text: str) -> str:
    """``name : type  description`` lines of the field sections as numpydoc's two lines."""
    lines = text.split("\n")
    out: list[str] = []
    section = None
    for i, line in enumerate(lines):
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and set(nxt.strip()) == {"-"} and not line.startswith(" "):
            section = line.strip().lower()
        elif section in _FIELD_SECTIONS and not line.startswith(" "):
            m = _COMPACT.match(line)
            if m:
                out += [f"{m['name']} : {_plain(m['type'])}", f"    {m['desc']}"]
                continue
            m = _ENTRY.match(line)
            if m:
                out.append(f"{m['name']} : {_plain(m['type'])}")
                continue
        elif section in _TYPE_SECTIONS and line.strip() and not line.startswith(" "):
            out.append(_plain(line))  # the exception's type: shown verbatim
            continue
        out.append(line)
    return "\n".join(out)


def _walk(obj: griffe.Object, seen: set):
    if obj.path in seen:
        return
    seen.add(obj.path)
    yield obj
    for member in obj.members.values():
        if member.is_alias:
            continue
        yield from _walk(member, seen)


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx markup of every docstring of a loaded package (see module)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        for obj in _walk(pkg, set()):
            doc = obj.docstring
            if doc is None:
                continue
            doc.value = _roles(_fields(_tables(_literal_markers(doc.value))), pkg, obj)
