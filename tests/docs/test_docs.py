"""The documentation's promises, read from the files: the README stays short and keeps the test
command where ``.ci/run`` reads it; every relative link of the README, ``docs/`` and
``examples/`` names a file that exists, and a heading that exists where it names one, and so
does every link to a heading of ``docs/`` in a comment or docstring of the code; the
repository's copies of the binding contract and protocol (``docs/api.md``,
``docs/evaluation-protocol.md``) hold the same bytes as ``shared/`` where that folder sits
beside the repository."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


PAGES = sorted(
    [REPO / "README.md", REPO / "examples" / "README.md", *(REPO / "docs").rglob("*.md")]
)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
SHARED = REPO.parent / "shared"
COPIES = {"api.md": "API.md", "evaluation-protocol.md": "EVALUATION.md"}


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}


def links(page: Path) -> list[str]:
    return LINK.findall(FENCE.sub("", page.read_text()))


def test_the_readme_is_short_and_keeps_the_ci_test_command():
    lines = (REPO / "README.md").read_text().splitlines()
    assert len(lines) <= 250, len(lines)
    marker = lines.index("<!-- test-command -->")
    assert lines[marker + 1] == "```bash" and lines[marker + 3] == "```"
    assert "pytest" in lines[marker + 2]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_resolves(page):
    broken = []
    for link in links(page):
        if re.match(r"[a-z]+:", link):  # http:, https:, mailto:
            continue
        target, _, anchor = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        if not path.exists():
            broken.append(link)
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            broken.append(link)
    assert not broken, broken


CODE = ("service", "evaluation", "training", "benchmarks", "scripts", "tests")
CODE_LINK = re.compile(r"docs/([\w./-]+\.md)#([\w-]+)")


def test_every_heading_the_code_links_to_exists():
    """A comment says why in a line and links to docs/decisions.md for the rest: the link must
    land on its section, whose heading may since have been renamed."""
    broken = []
    headings = {page.relative_to(REPO / "docs").as_posix(): anchors(page)
                for page in (REPO / "docs").rglob("*.md")}  # fmt: skip
    for folder in CODE:
        for source in sorted((REPO / folder).rglob("*.py")):
            for number, line in enumerate(source.read_text().splitlines(), 1):
                for page, anchor in CODE_LINK.findall(line):
                    if anchor not in headings.get(page, ()):
                        broken.append(f"{source.relative_to(REPO)}:{number}: {page}#{anchor}")
    assert not broken, broken


@pytest.mark.parametrize("copy, original", COPIES.items())
def test_the_binding_documents_are_copied_in_step(copy, original):
    if not (SHARED / original).exists():
        pytest.skip(f"no {SHARED / original} beside the repository")
    assert (REPO / "docs" / copy).read_bytes() == (SHARED / original).read_bytes()
