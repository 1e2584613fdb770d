"""Every relative link in the README and docs/ leads somewhere: the file exists and, for
``file.md#anchor``, the file has that heading (GitHub's anchor rule: lower case, spaces to
'-', punctuation dropped)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def anchors(md: Path) -> set[str]:
    out = set()
    for line in FENCE.sub("", md.read_text()).splitlines():
        if line.startswith("#"):
            text = line.lstrip("#").strip().lower()
            text = re.sub(r"[^\w\- ]", "", text).replace(" ", "-")
            out.add(text)
    return out


def links(md: Path) -> list[str]:
    return [t for t in LINK.findall(FENCE.sub("", md.read_text()))
            if not re.match(r"^[a-z][a-z0-9+.-]*:", t)]  # http:, mailto: ... not checked


@pytest.mark.parametrize("md", DOCS, ids=lambda p: p.name)
def test_relative_links_resolve(md: Path) -> None:
    broken = []
    for target in links(md):
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve() if path else md
        if not dest.exists():
            shown = dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest
            broken.append(f"{target}: no {shown}")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.name}")
    assert not broken, f"{md.name}: " + "; ".join(broken)


# (examples/ is left out: the docs quote picamera2's examples/ too.)
PATH_REF = re.compile(r"(?<![\w/.-])((?:docs|kmea|kmead|kmea_tui|tests|scripts|deploy|tools|"
                      r"constraints)/[\w/.-]*\w\.(?:md|py|sh|toml|txt|c|service))(?![\w])")
PRODUCT = [*DOCS, *sorted(ROOT.glob("kmea*/**/*.py")), ROOT / "Makefile",
           *sorted((ROOT / "deploy").iterdir())]


@pytest.mark.parametrize("path", PRODUCT, ids=lambda p: str(p.relative_to(ROOT)))
def test_files_named_in_docs_and_code_exist(path: Path) -> None:
    """A path named in prose or a comment (``docs/x.md``, ``kmead/tools/host.py``) exists
    (as written from the repository's root)."""
    missing = sorted({ref for ref in PATH_REF.findall(path.read_text(errors="replace"))
                      if not (ROOT / ref).exists()})
    assert not missing, f"{path.relative_to(ROOT)} names missing files: {missing}"
