"""README and docs/ point only at files a clone of the repository has."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
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


# any link: a relative target with an anchor, or an anchor alone
ANCHORED = re.compile(r"\]\(([^)\s#]*)#([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to -."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of a markdown page's headings (outside code blocks)."""
    found, fenced = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6} ", line):
            found.add(slug(line.lstrip("#")))
    return found


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_anchors_name_a_heading_of_their_page(page):
    for match in ANCHORED.finditer(page.read_text()):
        target, anchor = match.groups()
        if target.startswith(("http://", "https://")):
            continue
        linked = (page.parent / target).resolve() if target else page
        assert anchor in anchors(linked), f"{page.name}: no heading for {match[0]}"


def test_slugs_follow_github(tmp_path):  # the rule itself
    assert slug(" What the first planning's gap responds to") == (
        "what-the-first-plannings-gap-responds-to"
    )
    assert slug(" The `--book-inertia` run (I = 1)") == "the---book-inertia-run-i--1"
    page = tmp_path / "page.md"
    page.write_text("# Top\n```bash\n# not a heading\n```\n## Two words\n")
    assert anchors(page) == {"top", "two-words"}


def python_block(page: Path, line: str) -> str:
    """The first ```python block after the whole line `line` of `page`."""
    text = page.read_text()
    start = text.index("```python\n", text.index(f"\n{line}\n")) + len("```python\n")
    return text[start : text.index("```\n", start)]


def test_readmes_model_example_runs_as_written(tmp_path, monkeypatch):
    """README's model example, on a small batch where the quick start puts one,
    with the fit made tiny (the one change, checked to apply)."""
    from tasks import collect
    from tasks.acrobot import AcrobotParams

    code = python_block(ROOT / "README.md", "## The model")
    sizes = "n_support=500, n_sweeps=60"
    assert sizes in code
    code = code.replace(sizes, "n_support=30, n_sweeps=4, n_hyper=200, progress=False")
    batch = collect.collect(
        "acrobot",
        [AcrobotParams(m, 1.0) for m in (0.8, 1.0, 1.2)],
        episodes_per_instance=2,
        max_steps=60,
        rng=np.random.default_rng(0),
    ).transitions
    (tmp_path / "runs" / "acrobot_swingup").mkdir(parents=True)
    batch.save(tmp_path / "runs" / "acrobot_swingup" / "batch.npz")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["model"].weights.shape[1] == 2  # fitted on all but one
    assert namespace["mean"].shape == (50, 4)
    assert (tmp_path / "runs" / "model.npz").exists()
    # and the planning example after it, on what the model example left
    code = python_block(
        ROOT / "README.md",
        "snippet above. The task is yours: a reward and a terminal test on arrays of",
    )
    exec(compile(code, "README.md", "exec"), namespace)
    result = namespace["result"]
    assert result.steps.shape == (100,) and namespace["agent"].weights.shape[0] == 3
    assert (result.steps <= 200).all()


def test_readmes_dataset_example_runs_on_the_default_generate_run(
    tmp_path, monkeypatch
):
    from tasks import generate

    monkeypatch.chdir(tmp_path)
    generate.main(["--domain", "acrobot", "--max-steps", "5", "--no-progress"])
    namespace: dict = {}
    code = python_block(
        ROOT / "README.md",
        "To read a run (here the first command's, `runs/data`, 4 instances):",
    )
    exec(compile(code, "README.md", "exec"), namespace)
    assert set(namespace["data"].instances) == {0, 3}
    assert namespace["ds"].parameters.values.shape == (4, 6)


def test_the_version_to_cite_is_the_packages():
    """README's Citing names the version ``pyproject.toml`` gives, which the
    installed package reports as ``hipmdp.__version__``."""
    import tomllib

    import hipmdp

    with open(ROOT / "pyproject.toml", "rb") as fh:
        version = tomllib.load(fh)["project"]["version"]
    assert hipmdp.__version__ == version
    assert f"(`hipmdp` {version}, `pyproject.toml`;" in (ROOT / "README.md").read_text()
