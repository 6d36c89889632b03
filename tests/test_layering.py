"""The house rules of the package (issue 35, item 4; the layers are those of
docs/architecture.md, read from the page itself).

The import graph is built from the source with ``ast``, importing nothing: an edge for every
``import pfnet.x`` and ``from pfnet.x import y`` (``y`` a submodule: an edge to it), at module
level and inside functions alike. An import inside a function is still an import: it runs
the imported module's code when the function does, and a circle through one breaks as soon
as both ends are first imported from the other side, so none is exempt. The one import that
is not counted is Python's own of a module's parent package (``pfnet.io.clouds`` runs
``pfnet/io/__init__.py`` first), which no source line asks for; ``pfnet/__init__.py``'s lazy
names (``pfnet.complete``...) are strings resolved on first use, checked separately below.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "python" / "pfnet"
ARCHITECTURE = PACKAGE.parent.parent / "docs" / "architecture.md"
MAX_TOP_LEVEL = 14
# Not modules of the source tree: the compiled extension (its stub is read as a leaf) and the
# shipped model files.
NOT_COUNTED = {"_core", "weights"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules["pfnet._core"] = PACKAGE / "_core.pyi"
    return modules


def _imports(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``path`` (module ``name``) imports."""
    if path.suffix != ".py":
        return set()

    def known(dotted: str) -> str | None:
        while dotted and dotted not in modules:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {known(a.name) for a in node.names if a.name.split(".")[0] == "pfnet"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: the package pfnet uses none, but read them right
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            if base.split(".")[0] != "pfnet":
                continue
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.add(submodule if submodule in modules else known(base))
    return found - {None, name}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, name, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _layers() -> list[set[str]]:
    """The layers of the architecture page, lowest first: the ``text`` block under "## The
    layers", one layer a line (highest first), its entries before two spaces, separated by
    commas or ``|``."""
    page = ARCHITECTURE.read_text(encoding="utf-8")
    section = page.split("## The layers", 1)[1]
    block = re.search(r"```text\n(.*?)```", section, re.S)
    assert block, "docs/architecture.md: no ```text block of layers under '## The layers'"
    layers = []
    for line in block.group(1).splitlines():
        names = re.split(r"\s{2,}", line.strip())[0]
        if names:
            layers.append({n.strip() for n in re.split(r"[,|]", names)})
    return layers[::-1]


def _entry(module: str) -> str:
    """The top-level entry a module belongs to: ``pfnet.io.clouds`` -> ``io``, ``pfnet`` ->
    ``__init__``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_no_import_circle():
    cycles = _cycles(_graph())
    assert not cycles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_top_level_holds_at_most_fourteen_entries():
    entries = {p.stem for p in PACKAGE.glob("*.py")}
    entries |= {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    entries -= NOT_COUNTED
    assert len(entries) <= MAX_TOP_LEVEL, sorted(entries)


def test_the_layers_of_the_architecture_page_hold_every_entry_once():
    layers = _layers()
    named = [name for layer in layers for name in layer]
    assert len(named) == len(set(named)), named
    entries = {_entry(m) for m in _modules()}
    assert entries == set(named), (sorted(entries - set(named)), sorted(set(named) - entries))


def test_each_layer_imports_only_the_layers_below_it():
    """Entries of one layer never import each other, except in the lowest (the base modules
    share it); a command imports the library, never another command."""
    layers = _layers()
    rank = {name: i for i, layer in enumerate(layers) for name in layer}
    wrong = []
    for module, imported in sorted(_graph().items()):
        for other in sorted(imported):
            a, b = _entry(module), _entry(other)
            if a == b:
                if a == "commands" and "pfnet.commands" not in (module, other):
                    wrong.append(f"{module} -> {other} (a command imports another)")
                continue
            if rank[b] > rank[a] or (rank[b] == rank[a] and rank[a] > 0):
                wrong.append(f"{module} -> {other} ({a} may not import {b})")
    assert not wrong, "\n".join(wrong)


def test_the_lazy_public_names_resolve_to_library_modules():
    """``pfnet/__init__.py`` imports the base only; ``pfnet.complete`` and the other lazy
    names are strings naming a library module (not a command) that defines them."""
    tree = ast.parse((PACKAGE / "__init__.py").read_text(encoding="utf-8"))
    lazy = next(
        ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "_LAZY"
    )
    modules = _modules()
    for name, module in lazy.items():
        assert module in modules and _entry(module) not in {"commands", "cli"}, module
        source = ast.parse(modules[module].read_text(encoding="utf-8"))
        defined = {getattr(n, "name", None) for n in source.body}
        assert name in defined, (name, module)
    base = _layers()[0]
    assert {_entry(m) for m in _graph()["pfnet"]} <= base
