"""The architecture as the code has it: layers, no import cycles, small modules, one sensor model.

Read from the source with ``ast`` (nothing is imported): every ``import`` of a gravcal module, at the top
of a file or inside a function, is an edge of the module graph, and so is each package above the imported
module (importing ``a.b.c`` runs ``a.b``'s ``__init__`` first, with everything it imports), but for the
importer's own packages, which are loaded before it.
"""
from __future__ import annotations

import ast
import functools
import re
import tomllib
from pathlib import Path

import pytest

from gravcal.core.model.terms import REGISTRY

ROOT = Path(__file__).resolve().parents[2]
LAYERS = {"core": "gravcal.core", "drivers": "gravcal.drivers", "daemon": "gravcal.daemon", "io": "gravcal.io",
          "cli": "gravcal.cli", "clients": "gravcal.clients", "api": "gravcal"}
MAX_LINES = 600


def modules() -> dict[str, Path]:
    out = {}
    for folder, package in LAYERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            name = ".".join((package, *parts))
            out[name.removesuffix(".__init__")] = path
    return out


@functools.cache
def parsed(path: Path) -> ast.Module:
    """The file's syntax tree, parsed once for the tests that read it (none of them changes it)."""
    return ast.parse(path.read_text(), filename=str(path))


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The gravcal modules ``name`` imports, anywhere in the file."""
    tree = parsed(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            candidates = [target] + [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        else:
            continue
        found |= {c for c in candidates if c in known and c != name}
    return found | {p for m in found for p in ancestors(m) if p in known and p not in ancestors(name)}


def ancestors(name: str) -> list[str]:
    """The packages Python imports (their ``__init__``, with everything it imports) before module ``name``."""
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    known = modules()
    return {m: imports(m, p, known) for m, p in known.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The graph's strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles(graph):
    """No cycle, lazy imports included (a function-level import does not make a cycle acceptable)."""
    assert not cycles(graph), f"import cycles: {cycles(graph)}"


def test_a_lazy_import_of_a_leaf_module_counts_its_package_init(tmp_path):
    """A function imports a module that imports nothing, but its package's __init__ imports the caller's
    importer: a cycle, found through the package edge (without it the graph would be acyclic)."""
    files = {"core/model/filters.py": "def design():\n    from ..detectors.butterworth import butter_sos\n",
             "core/model/__init__.py": "from .filters import design\n",
             "core/detectors/__init__.py": "from .windowing import detect\n",
             "core/detectors/windowing.py": "from ..model import design\n",
             "core/detectors/butterworth.py": "import math\n"}
    known = {}
    for rel, text in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        known[".".join(("gravcal", *Path(rel).with_suffix("").parts)).removesuffix(".__init__")] = path
    fake = {m: imports(m, path, known) for m, path in known.items()}
    assert "gravcal.core.detectors" in fake["gravcal.core.model.filters"]
    assert cycles(fake) == [["gravcal.core.detectors", "gravcal.core.detectors.windowing", "gravcal.core.model",
                             "gravcal.core.model.filters"]]


def test_layers_point_one_way(graph):
    """core imports neither drivers nor daemon; drivers never import daemon; the real drivers never
    import their test rigs (drivers/rigs: emulator, fakes, HIL); daemon/ is gravcald alone: it imports
    none of the offline packages (io, cli, clients); io imports no daemon or command line; nothing
    below the Python API (api/, imported as gravcal) imports it, but for its shared errors, output
    helpers, bounded JSON parsing and release number (gravcal.errors, gravcal.closed_pipe,
    gravcal.jsonbounds, gravcal._version)."""
    shared = {"gravcal.errors", "gravcal.closed_pipe", "gravcal.jsonbounds", "gravcal._version"}
    api = {"gravcal", *(m for m in graph if m.startswith("gravcal.") and not m.startswith(tuple(
        f"{p}." for p in LAYERS.values() if p != "gravcal")) and m not in LAYERS.values())} - shared
    bad = []
    for m, deps in graph.items():
        for d in deps:
            if m not in api and d in api:
                bad.append((m, d))
            if m.startswith("gravcal.core") and not d.startswith("gravcal.core"):
                bad.append((m, d))
            if m.startswith("gravcal.drivers") and d.startswith("gravcal.daemon"):
                bad.append((m, d))
            if m.startswith("gravcal.daemon") and d.startswith(("gravcal.io", "gravcal.cli", "gravcal.clients")):
                bad.append((m, d))
            if m.startswith("gravcal.io") and d.startswith(("gravcal.daemon", "gravcal.cli", "gravcal.clients")):
                bad.append((m, d))
            if (m.startswith("gravcal.drivers") and not m.startswith("gravcal.drivers.rigs")
                    and d.startswith("gravcal.drivers.rigs")):
                bad.append((m, d))
    assert not bad, bad


SOURCE_SUFFIXES = ("*.py", "*.c", "*.h")


def test_no_source_file_over_the_limit():
    """Python and C alike: a compiled kernel too long to read is split into files, one concern each."""
    files = [p for folder in (*LAYERS, "bench", "tests") for suffix in SOURCE_SUFFIXES
             for p in (ROOT / folder).rglob(suffix)]
    long = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"over {MAX_LINES} lines: {long}"


def included_headers(source: Path) -> set[Path]:
    """The project's headers a C file includes ("..." includes, resolved beside it), theirs included."""
    found: set[Path] = set()
    todo = [source]
    while todo:
        current = todo.pop()
        for name in re.findall(r'^\s*#\s*include\s+"([^"]+)"', current.read_text(), re.MULTILINE):
            header = (current.parent / name).resolve()
            if header not in found and header.is_file():
                found.add(header)
                todo.append(header)
    return found


def test_every_c_file_is_built_and_its_headers_rebuild_it():
    """Every C file of the package is a source of exactly one extension in pyproject.toml, and each
    extension's depends list every header its sources include (a changed header rebuilds it)."""
    extensions = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["ext-modules"]
    listed = [s for ext in extensions for s in ext["sources"]]
    found = [str(p.relative_to(ROOT)) for folder in LAYERS for p in (ROOT / folder).rglob("*.c")]
    assert sorted(listed) == sorted(found), ("not built:", sorted(set(found) - set(listed)),
                                             "listed twice or absent:", sorted(set(listed) - set(found)))
    missing = {}
    for ext in extensions:
        needed = set().union(*(included_headers(ROOT / s) for s in ext["sources"]))
        declared = {(ROOT / d).resolve() for d in ext.get("depends", [])}
        if needed - declared:
            missing[ext["name"]] = sorted(str(h.relative_to(ROOT)) for h in needed - declared)
    assert not missing, missing


def test_every_package_is_installed():
    """pyproject's package list holds every folder with an __init__.py (an editable install would hide
    a missing one; a wheel would not)."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {m for m, p in modules().items() if p.name == "__init__.py"}
    assert found == listed, (sorted(found - listed), sorted(listed - found))


def test_no_code_outside_a_term_switches_on_its_name():
    """A term's name appears as a string only in its own module (and the registry that lists it): every
    other place enumerates the registry. The forward chain's geometry term ("axes") and the gyro model
    (core/model/enc03j.py, which defines the gyro's terms) are the model's structure, not switches."""
    names = {s.name for s in REGISTRY.values()} | {s.catalogue_name for s in REGISTRY.values()}
    structural = {"axes"}
    switches = names - structural
    allowed_dirs = {ROOT / "core" / "model" / "terms"}
    allowed_files = {ROOT / "core" / "model" / "enc03j.py"}
    hits = []
    for folder in LAYERS:
        for path in (ROOT / folder).rglob("*.py"):
            if path.parent in allowed_dirs or path in allowed_files:
                continue
            for node in ast.walk(parsed(path)):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in switches:
                    hits.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.value!r}")
    assert not hits, hits


def test_no_comment_tells_the_project_history():
    """Comments and docstrings say why, not which issue or helper wrote the code."""
    pattern = re.compile(r"\b(issue \d+|H-(estimate|detect|twelve)|written in parallel|the previous behaviour)\b",
                         re.IGNORECASE)
    hits = []
    for folder in LAYERS:
        for path in (ROOT / folder).rglob("*.py"):
            for i, line in enumerate(path.read_text().splitlines(), 1):
                if pattern.search(line):
                    hits.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:80]}")
    assert not hits, hits
