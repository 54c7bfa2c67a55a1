"""MkDocs hook: check the module list of ``docs/method.md`` against the sources' imports.

The page lists every module of ``bayesreg/`` between ``<!-- module-graph:begin -->`` and
``<!-- module-graph:end -->``, one table row each: the module, its job, and the bayesreg
modules it imports.  This hook reads the imports of the sources (module level and inside
functions alike) and logs a warning, which fails ``mkdocs build --strict``, where

* a module is missing from the list, or listed but not in the sources;
* a module's listed imports differ from its sources' imports;
* a module imports one listed below it (an import against the data flow, or a cycle).

So the graph drawn in the documentation is the code's.  Registered under ``hooks:`` in
``mkdocs.yml``.
"""

from __future__ import annotations

import ast
import logging
import re
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.module_graph")

BEGIN, END = "<!-- module-graph:begin -->", "<!-- module-graph:end -->"
PACKAGE = "bayesreg"


def _short(name: str) -> str:
    return name if name == PACKAGE else name.removeprefix(PACKAGE + ".")


def source_graph(root: Path) -> dict[str, set[str]]:
    """``{module: modules of the package it imports}``, short names (``kernels.rwmh``)."""
    mods: dict[str, Path] = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    graph = {}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                           for a in node.names]
            else:
                continue
            found |= {t for t in targets if t in mods and t != name}
        graph[_short(name)] = {_short(t) for t in found}
    return graph


def listed_graph(markdown: str) -> list[tuple[str, set[str]]]:
    """The rows of the list: ``[(module, its listed imports)]`` in the page's order."""
    block = markdown.split(BEGIN, 1)[1].split(END, 1)[0]
    rows = []
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0].startswith("`"):
            continue
        rows.append((cells[0].strip("`"), set(re.findall(r"`([^`]+)`", cells[-1]))))
    return rows


def check(markdown: str, root: Path) -> list[str]:
    """What differs between the page's list and the sources (empty: nothing)."""
    graph = source_graph(root)
    rows = listed_graph(markdown)
    listed = [m for m, _ in rows]
    problems = []
    for m in sorted(set(graph) - set(listed)):
        problems.append(f"module {m} is not listed")
    for m in sorted(set(listed) - set(graph)):
        problems.append(f"{m} is listed but is not a module of {root}")
    position = {m: i for i, m in enumerate(listed)}
    for m, imports in rows:
        if m not in graph:
            continue
        if imports != graph[m]:
            missing, extra = sorted(graph[m] - imports), sorted(imports - graph[m])
            if missing:
                problems.append(f"{m} imports {', '.join(missing)}, not in its row")
            if extra:
                problems.append(f"{m}'s row lists {', '.join(extra)}, which it does not import")
        below = sorted(t for t in graph[m] if position.get(t, -1) > position[m])
        if below:
            problems.append(f"{m} imports {', '.join(below)}, listed below it (against the "
                            "data flow, or a cycle)")
    return problems


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    if BEGIN not in markdown:
        return markdown
    root = Path(config["config_file_path"]).resolve().parent / PACKAGE
    for problem in check(markdown, root):
        log.warning("%s, module graph: %s", page.file.src_path, problem)
    return markdown
