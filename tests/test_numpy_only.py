"""The algorithm modules import only numpy, the standard library and each other.

Two checks: every import statement in their source (also those inside functions, which a
plain import would not run), and the modules actually loaded by importing them in a fresh
interpreter.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "kmea"
# Whole packages (every module, subpackages too) and single modules.
PACKAGES = ("robots", "stats", "estimators", "geometry")
MODULES = ("maps/model.py", "maps/aruco_names.py", "timing.py")
ALGORITHM_FILES = sorted([*(PKG / m for m in MODULES),
                          *(p for pkg in PACKAGES for p in (PKG / pkg).rglob("*.py"))])


def _dotted(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


# A package's __init__ runs before its modules: kmea's own, and those of kmea.maps.
ALGORITHM_MODULES = {"kmea", "kmea.maps"} | {_dotted(p) for p in ALGORITHM_FILES}
BACKPORTS: set[str] = set()


def _allowed(module: str) -> bool:
    top = module.split(".")[0]
    if top == "kmea":
        return module in ALGORITHM_MODULES
    return top == "numpy" or top in sys.stdlib_module_names or top in BACKPORTS


def _imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                raise AssertionError(f"{path}:{node.lineno}: use absolute imports")
            out.append((node.lineno, node.module or ""))
        elif (isinstance(node, ast.Call) and isinstance(node.func, (ast.Name, ast.Attribute))
              and getattr(node.func, "id", getattr(node.func, "attr", "")) in
              ("import_module", "__import__") and node.args
              and isinstance(node.args[0], ast.Constant)):
            out.append((node.lineno, node.args[0].value))
    return out


def test_the_file_list_covers_the_estimators() -> None:
    names = {_dotted(p) for p in ALGORITHM_FILES}
    assert {"kmea.maps.model", "kmea.estimators.kmea", "kmea.estimators.lmea",
            "kmea.estimators.umeyama", "kmea.estimators.corner_pnp.fit", "kmea.stats.metrics",
            "kmea.robots.iir", "kmea.robots.poses", "kmea.robots.tracking.track"} <= names


def test_source_imports_are_numpy_and_stdlib_only() -> None:
    bad = [f"{p.relative_to(ROOT)}:{line}: imports {mod}"
           for p in ALGORITHM_FILES for line, mod in _imports(p) if not _allowed(mod)]
    assert bad == []


def test_the_checker_would_catch_a_forbidden_import(tmp_path: Path) -> None:
    f = tmp_path / "m.py"
    f.write_text("import numpy as np\n\ndef g():\n    import cv2\n    from zmq import Context\n")
    assert [m for _, m in _imports(f) if not _allowed(m)] == ["cv2", "zmq"]
    assert not _allowed("tomli_w") and not _allowed("kmea.vision.camera")
    assert _allowed("numpy.linalg") and _allowed("collections.abc")


PROBE = """
import json, sys, sysconfig
before = set(sys.modules)  # .pth hooks of site-packages load before us
for m in MODULES:
    __import__(m)
import kmea.estimators as e
for n in ("kmea", "lmea", "umeyama"):
    e.get(n)
site = tuple({sysconfig.get_paths()[k] for k in ("purelib", "platlib")})
new = {k: getattr(m, "__file__", None) or "" for k, m in list(sys.modules.items())
       if k not in before}
print(json.dumps(sorted({k.split(".")[0] for k, f in new.items() if f.startswith(site)})))
"""


def test_importing_them_loads_no_third_party_module() -> None:
    # Third-party code is whatever our imports load from site-packages; only numpy may be.
    code = PROBE.replace("MODULES", repr(sorted(ALGORITHM_MODULES)))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    third_party = json.loads(out)
    assert "numpy" in third_party  # the probe does see site-packages
    assert [t for t in third_party if t not in {"numpy", *BACKPORTS}] == []
