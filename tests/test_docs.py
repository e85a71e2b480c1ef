"""The documentation a user reads first: the README's two commands and the links between the
README, the notes in docs/ and the model record, which point at files that must exist."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "veckm_flow" / "weights" / "MODEL.md",
        *sorted((ROOT / "docs").glob("*.md"))]
# [text](target) or ![alt](target); external and in-page links are not files
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def relative_links(path: Path) -> list[str]:
    return [t for t in LINK.findall(path.read_text(encoding="utf-8")) if not re.match(r"[a-z]+:", t)]


def test_link_pattern_finds_files_and_images_but_not_urls(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("[a](docs/x.md) ![b](img.png) [c](https://e.org/y) [d](z.md#part)", encoding="utf-8")
    assert relative_links(page) == ["docs/x.md", "img.png", "z.md"]


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_at_a_file(path):
    missing = [t for t in relative_links(path) if not (path.parent / t).exists()]
    assert not missing, f"{path.relative_to(ROOT)} links to missing files: {missing}"


def test_readme_opens_with_the_setup_and_test_commands():
    # The README's contract with a fresh machine (and .ci/run): set up + demo, then the tests.
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    block = lines[lines.index("```bash") + 1: lines.index("```bash") + 3]
    assert block == [
        'python3 -m venv .venv && .venv/bin/pip install -e ".[all]" && .venv/bin/evseg demo',
        ".venv/bin/python -m pytest -q",
    ]


def github_anchor(heading: str) -> str:
    """The id GitHub gives a markdown heading: lower case, punctuation dropped, spaces -> '-'.

    >>> github_anchor("Pipeline: segment a recording")
    'pipeline-segment-a-recording'
    """
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_in_page_links_of_the_readme_name_its_headings():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    anchors = {github_anchor(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}
    targets = re.findall(r"\]\(#([^)\s]+)\)", text)
    assert len(targets) >= 12  # the contents line
    assert not [t for t in targets if t not in anchors], "README links to headings it does not have"
