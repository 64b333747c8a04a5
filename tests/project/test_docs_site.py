"""The documentation site: it builds offline with no warning, every image and internal link of the built pages
resolves, and every Python block of its pages runs as written (as the README's do, tests/project/test_docs.py)."""

import os
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

import sb3_sera
from tests.helpers import ROOT
from tests.project.test_docs import PYTHON_BLOCKS, run_block_as_written

DOCS = ROOT / "docs"
PAGES = sorted(path for path in DOCS.rglob("*.md") if "_build" not in path.parts)
#: Every ```python block of the pages; a block the README holds too runs with the README's (test_docs.py)
DOCS_BLOCKS = list(
    dict.fromkeys(
        (path.relative_to(DOCS).as_posix(), block)
        for path in PAGES
        for block in re.findall(r"^```python\n(.*?)^```$", path.read_text(), flags=re.DOTALL | re.MULTILINE)
        if block not in PYTHON_BLOCKS
    )
)


def sphinx_build(out: Path) -> subprocess.CompletedProcess:
    """``make docs``'s build: warnings are errors (all of them reported, ``--keep-going``), every reference checked."""
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-n", "-q", "-b", "html", str(DOCS), str(out)]
    return subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True, timeout=900)


class PageLinks(HTMLParser):
    """The ids a built page defines and the files and anchors it points to (images, links, scripts, stylesheets)."""

    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()
        self.targets: list[tuple[str, str]] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        attributes = dict(attrs)
        if attributes.get("id"):
            self.ids.add(str(attributes["id"]))
        for name in ("src", "href"):
            value = attributes.get(name)
            if value and tag in ("img", "a", "script", "link"):
                self.targets.append((tag, value))


def parse(page: Path) -> PageLinks:
    parser = PageLinks()
    parser.feed(page.read_text(encoding="utf-8"))
    return parser


def broken_targets(site: Path) -> list[str]:
    """Every image, stylesheet, script and internal link of the site whose file or anchor does not exist."""
    pages = {page.resolve(): parse(page) for page in site.rglob("*.html")}
    broken = []
    for page, links in pages.items():
        for tag, target in links.targets:
            parts = urlsplit(target)
            if parts.scheme or parts.netloc:  # an external address: not ours to check offline
                continue
            file = (page.parent / unquote(parts.path)).resolve() if parts.path else page
            where = f"{page.relative_to(site.resolve())}: <{tag}> {target}"
            if not file.is_file():
                broken.append(f"{where} (no file)")
            elif parts.fragment and file.suffix == ".html" and unquote(parts.fragment) not in pages[file].ids:
                broken.append(f"{where} (no anchor)")
    return broken


def test_the_site_builds_without_a_warning_and_every_image_and_link_resolves(tmp_path):
    site = tmp_path / "html"
    built = sphinx_build(site)
    assert built.returncode == 0, f"the docs build warns:\n{built.stderr[-6000:]}"
    assert not built.stderr.strip(), built.stderr
    # The pages of the issue: the guide, one per algorithm, results, speed, the API reference, developer, changelog
    expected = [
        "index",
        "guide/install",
        "guide/quickstart",
        "guide/multi_agent",
        "guide/experiments",
        "guide/developer",
        "modules/serasac",
        "modules/ctde",
        "modules/sunrise",
        "modules/ace",
        "modules/iet",
        "results/index",
        "results/report",
        "speed",
        "api/common",
        "api/ctde",
        "api/sera",
        "api/baselines",
        "api/study",
        "misc/changelog",
        "SPEC",
    ]
    assert [name for name in expected if not (site / f"{name}.html").is_file()] == []
    assert broken_targets(site) == []
    # Every figure of the ledger's report is on the site, and the parameters come from the docstrings
    report = (site / "results" / "report.html").read_text(encoding="utf-8")
    figures = sorted(path.name for path in (DOCS / "results").glob("*.png"))
    assert figures and all(name in report for name in figures)
    serasac = (site / "modules" / "serasac.html").read_text(encoding="utf-8")
    assert 'id="sb3_sera.sera.sera.SERASAC"' in serasac and "critic_lr_max" in serasac
    changelog = (site / "misc" / "changelog.html").read_text(encoding="utf-8")
    assert f"{sb3_sera.__version__} (" in changelog


def test_the_docs_have_python_blocks_and_no_other_code_blocks_that_would_escape_the_runner():
    assert len(DOCS_BLOCKS) >= 5
    # Python in a reStructuredText page or a MyST code-block directive would not be run: every example is a ```python
    for path in [*PAGES, *DOCS.rglob("*.rst")]:
        text = path.read_text()
        assert not re.search(r"code-block::?\s*python|\{code-block\}\s*python", text), path


def test_the_version_is_the_one_cited_and_released():
    version = sb3_sera.__version__
    for path in (DOCS / "index.md", ROOT / "README.md"):
        assert f"version = {{{version}}}" in path.read_text(), path
    released = re.search(r"^## (\S+) \((\d{4}-\d{2}-\d{2})\)$", (ROOT / "CHANGELOG.md").read_text(), flags=re.MULTILINE)
    assert released is not None and released.group(1) == version


@pytest.mark.parametrize(
    ("page", "block"), DOCS_BLOCKS, ids=[f"{page}-{index}" for index, (page, _) in enumerate(DOCS_BLOCKS)]
)
def test_docs_python_block_runs_as_written(page, block, tmp_path):
    run_block_as_written(block, tmp_path, page)
