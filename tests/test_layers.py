"""The layer rules of the architecture (docs/architecture.md), enforced on the source.

- ``kmea`` (the library) imports neither ``kmead`` (the daemon) nor ``kmea_tui`` (the UI),
  with no exception: the ``kmea`` command's daemon-side tools are added above both, in
  ``kmead/tools/kmea_cli.py``.
- ``kmea_tui`` imports from ``kmea`` only the wire protocol and the stdlib-only helpers of
  :data:`TUI_MAY_IMPORT`, and never ``kmead``; those modules import only the standard
  library (and each other). A subprocess checks that importing the UI loads neither
  ``kmead`` nor OpenCV nor numpy.
- Ranks (:data:`RANKS`): every package has a rank, and a module never imports a module of a
  higher rank (front-ends at the top, the geometry and the wire format at the bottom).
  Packages of one rank may import each other; the circle check below still holds for them.
- No import circles inside a package: every import counts (module level, inside functions,
  under ``TYPE_CHECKING``), with no exception.

Imports are read from the AST of every module, and dynamic imports by name
(``import_module("kmead.benchmarks.daemon")``, ``"kmead.benchmarks.daemon:run"`` tables) are
found as string constants that name a module of the other layer.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("kmea", "kmead", "kmea_tui")

# kmea.wire: the protocol and its stdlib-only helpers, nothing else.
TUI_MAY_IMPORT = {"kmea", "kmea.wire"} | {
    f"kmea.wire.{p.stem}" for p in (ROOT / "kmea" / "wire").glob("*.py") if p.stem != "__init__"}
# Functions' lazy imports that do not count as edges for the cycle check (module -> targets).
# Backports of standard modules, for Python versions before they joined the stdlib.
STDLIB_BACKPORTS = {"tomli"}  # tomllib before 3.11

# The import ranks, lowest first: a module may import its own rank and the ranks below it.
# A module's rank is that of the longest entry that is it or contains it.
RANKS: tuple[tuple[str, ...], ...] = (
    # Foundations: numbers, frames, the wire format; nothing of KMEA above them.
    ("kmea", "kmea.wire", "kmea.timing", "kmea.progress", "kmea.frame", "kmea.geometry",
     "kmea.stats", "kmead"),
    ("kmea.maps",),
    ("kmea.estimators",),
    ("kmea.vision", "kmea.robots", "kmea.fixed_camera", "kmea.camera_advice"),
    ("kmea.sim", "kmea.recordings"),
    ("kmea.sources", "kmea.pipeline", "kmea.survey"),
    # The lab: experiments and benchmarks, user-facing but above the product.
    ("kmea.experiments",),
    ("kmea.benchmarks",),
    # The library's front-ends: argument parsing and wiring of the `kmea` command.
    ("kmea.cli",),
    # The daemon's services: the configuration (the keys, their checks, the start-up plan),
    # the outputs (files, the relay, Zenoh), the sockets and the service shell.
    ("kmead.config",),
    ("kmead.outputs",),
    ("kmead.net",),
    ("kmead.viewers",),
    ("kmead.run", "kmead.fusion"),
    ("kmea_tui",),
    # The daemon's front-ends: kmead, kmea's daemon-side commands, the daemon's benchmarks.
    ("kmead.cli", "kmead.tools", "kmead.benchmarks"),
)
_RANK_OF = {name: i for i, tier in enumerate(RANKS) for name in tier}

_MODULE_STRING = re.compile(r"^(kmead|kmea_tui|kmea)(\.[A-Za-z_]\w*)*(:\w+)?$")


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # the imported module (dotted)
    line: int
    lazy: bool  # inside a function


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_module(dotted: str) -> bool:
    base = ROOT.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imports_of(path: Path) -> list[Import]:
    """Every import of one file (relative ones resolved), with dynamic imports by name."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out: list[Import] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef,
                                               ast.Lambda))
            if isinstance(child, ast.Import):
                out.extend(Import(name, a.name, child.lineno, lazy) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    anchor = package.split(".")
                    anchor = anchor[:len(anchor) - (child.level - 1)]
                    base = ".".join([*anchor, base] if base else anchor)
                for a in child.names:
                    sub = f"{base}.{a.name}"
                    out.append(Import(name, sub if _is_module(sub) else base, child.lineno,
                                      lazy))
            elif isinstance(child, ast.Constant) and isinstance(child.value, str) \
                    and _MODULE_STRING.match(child.value) and "." in child.value:
                target = child.value.partition(":")[0]
                if target.split(".")[0] in PACKAGES and _is_module(target):
                    out.append(Import(name, target, child.lineno, True))
            visit(child, inner)

    visit(tree, False)
    return out


def all_imports() -> list[Import]:
    return [imp for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))
            for imp in imports_of(p)]


def top(dotted: str) -> str:
    return dotted.split(".")[0]


def test_the_library_imports_neither_the_daemon_nor_the_ui() -> None:
    bad = set()
    where = {}
    for imp in all_imports():
        if top(imp.module) != "kmea" or top(imp.target) not in ("kmead", "kmea_tui"):
            continue
        bad.add((imp.module, imp.target))
        where[(imp.module, imp.target)] = imp.line
    assert not bad, "kmea must not import kmead/kmea_tui: " + ", ".join(
        f"{m} (line {where[(m, t)]}) imports {t}" for m, t in sorted(bad))


def test_the_ui_imports_only_the_wire_protocol() -> None:
    bad = [f"{imp.module}:{imp.line} imports {imp.target}" for imp in all_imports()
           if top(imp.module) == "kmea_tui"
           and (top(imp.target) == "kmead"
                or (top(imp.target) == "kmea" and imp.target not in TUI_MAY_IMPORT))]
    assert not bad, bad
    # ... and what it may import needs nothing but the standard library.
    stdlib = set(sys.stdlib_module_names) | {"__future__"} | STDLIB_BACKPORTS
    for mod in sorted(TUI_MAY_IMPORT):
        if not _is_module(mod):
            continue
        path = ROOT.joinpath(*mod.split("."))
        path = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
        for imp in imports_of(path):
            assert top(imp.target) in stdlib or imp.target in TUI_MAY_IMPORT, \
                f"{mod}:{imp.line} imports {imp.target}: the UI's imports must stay stdlib-only"


def test_importing_the_ui_loads_neither_the_daemon_nor_opencv() -> None:
    code = ("import sys, kmea_tui.app, kmea_tui.cli, kmea_tui.client; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('kmead', 'cv2', 'numpy', 'scipy')); print(' '.join(bad))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "", f"importing kmea_tui loaded: {r.stdout.strip()}"


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of a graph: its strongly connected components with more than one
    module (or a module importing itself), Tarjan's algorithm."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in edges.get(v, ()):
                out.append(sorted(comp))

    # Restored after: a raised limit would leak into later tests of this worker (a TOML
    # file nested 3000 deep would then parse instead of being refused as too deep).
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10000))
    try:
        for v in sorted(edges):
            if v not in index:
                strong(v)
    finally:
        sys.setrecursionlimit(limit)
    return out


def test_cycle_finder_finds_circles() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circles(package: str) -> None:
    edges: dict[str, set[str]] = {}
    for imp in all_imports():
        if top(imp.module) == package and top(imp.target) == package \
                and imp.target != imp.module and imp.target != package:
            edges.setdefault(imp.module, set()).add(imp.target)
    found = cycles(edges)
    assert not found, f"import circles in {package}: {found}"


def rank(module: str) -> int | None:
    """The rank of a module: that of the longest :data:`RANKS` entry it is or lies in."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        found = _RANK_OF.get(".".join(parts[:n]))
        if found is not None:
            return found
    return None


def test_rank_finds_the_longest_entry() -> None:
    assert rank("kmea.cli.map") == _RANK_OF["kmea.cli"]
    assert rank("kmea.frame") == rank("kmea") == 0
    assert rank("kmead.run.daemon") == _RANK_OF["kmead.run"] > rank("kmead.config.plan")
    assert rank("elsewhere.module") is None


def test_every_module_has_a_rank() -> None:
    unranked = sorted({module_name(p) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
                       if rank(module_name(p)) is None})
    assert not unranked, f"give these a rank in RANKS: {unranked}"


def test_no_module_imports_a_higher_rank() -> None:
    bad = []
    for imp in all_imports():
        here, there = rank(imp.module), rank(imp.target)
        if top(imp.target) in PACKAGES and here is not None and there is not None \
                and there > here:
            bad.append(f"{imp.module}:{imp.line} (rank {here}) imports {imp.target} "
                       f"(rank {there})")
    assert not bad, "an import upward:\n" + "\n".join(bad)


# The library starts no thread and leaves the scheduling to its caller: its per-frame
# computation (the pipeline and the fixed camera) imports no thread or executor module
# and sets no priority (the daemon's discovery thread does: kmead/run/discovery.py).
NO_THREADS = ("kmea.fixed_camera", "kmea.pipeline")
THREAD_MODULES = ("threading", "concurrent", "_thread", "multiprocessing", "zmq", "textual",
                  "picamera2")


def test_the_frame_computation_starts_no_thread_and_sets_no_priority() -> None:
    bad = []
    files = []
    for pkg in NO_THREADS:
        base = ROOT.joinpath(*pkg.split("."))
        files += [p for p in (base.with_suffix(".py"), *sorted(base.rglob("*.py")))
                  if p.is_file()]
    assert len(files) >= 8, files
    for p in files:
        bad += [f"{module_name(p)}:{imp.line} imports {imp.target}" for imp in imports_of(p)
                if imp.target.split(".")[0] in THREAD_MODULES]
        tree = ast.parse(p.read_text(encoding="utf-8"))
        bad += [f"{module_name(p)}:{n.lineno} calls {n.attr}" for n in ast.walk(tree)
                if isinstance(n, ast.Attribute) and n.attr in ("setpriority", "nice",
                                                                "sched_setaffinity")]
    assert not bad, bad
