"""README and docs/ point only at files a clone of the repository has."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# a link's target names a file or a folder (``f[k](s)`` in a formula is no link)
LINK = re.compile(r"\]\(([^)\s]*(?:/|\.\w+)(?:#[^)\s]*)?)\)")


def links(page: Path) -> list[str]:
    """The relative link targets of a markdown page, without their anchors."""
    targets = (m.group(1) for m in LINK.finditer(page.read_text()))
    return [
        t.split("#")[0]
        for t in targets
        if not t.startswith(("http://", "https://", "#", "mailto:"))
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve_inside_the_repository(page):
    for target in links(page):
        path = (page.parent / target).resolve()
        assert path.is_relative_to(ROOT), f"{page.name}: {target} is outside the repo"
        assert path.exists(), f"{page.name}: {target} does not exist"


def test_links_are_found(tmp_path):  # the pattern itself
    page = tmp_path / "page.md"
    page.write_text(
        "[a](docs/DESIGN.md) [b](../README.md#results) [c](#anchor) "
        "[d](https://x.org/y.md) f[k,a,d](s) [e](runs/)"
    )
    assert links(page) == ["docs/DESIGN.md", "../README.md", "runs/"]
    assert "docs/DESIGN.md" in links(ROOT / "README.md")
