"""The user documentation holds together: README.md stays a short guide with the two fresh-machine
commands, and every relative link in README.md and docs/*.md reaches a file (and heading) inside
the repository. Pure file reading: no network."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
USER_DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]
README_MAX_LINES = 300

LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
UUID = re.compile(r"\b[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}\b")
COMMIT_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
ISSUE_REF = re.compile(r"\bissues? #?[0-9]+", re.I)
# Built from parts so this file does not itself match what it looks for.
OUTSIDE_SPEC = re.compile("|".join([r"\.\./" + "shared", "shared" + "/spec"]))
# Generated and installed trees (egg-info copies the old README) are not the repository's own text.
SKIPPED_DIRS = {".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", "build"}


def relative_links(doc: Path) -> list[str]:
    """Link targets of a markdown file outside its code blocks, without web or mail links."""
    text = FENCE.sub("", doc.read_text(encoding="utf-8"))
    return [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def heading_anchors(doc: Path) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation dropped, spaces to -."""
    text = FENCE.sub("", doc.read_text(encoding="utf-8"))
    anchors: set[str] = set()
    for title in re.findall(r"^#{1,6} +(.+?) *$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")
        anchor, n = slug, 0
        while anchor in anchors:
            n += 1
            anchor = f"{slug}-{n}"
        anchors.add(anchor)
    return anchors


def link_problem(doc: Path, target: str) -> str | None:
    """Why a relative link of `doc` is broken, or None when it reaches an existing place."""
    path_part, _, anchor = target.partition("#")
    resolved = (doc.parent / path_part).resolve() if path_part else doc
    if not resolved.is_relative_to(ROOT):
        return "points outside the repository"
    if not resolved.exists():
        return "no such file"
    if anchor and resolved.suffix == ".md" and anchor not in heading_anchors(resolved):
        return f"no heading #{anchor} in {resolved.relative_to(ROOT)}"
    return None


@pytest.mark.parametrize("doc", USER_DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_reaches_a_place_inside_the_repository(doc: Path) -> None:
    broken = [
        f"{target}: {problem}"
        for target in relative_links(doc)
        if (problem := link_problem(doc, target))
    ]
    assert broken == [], f"{doc.relative_to(ROOT)}: {broken}"


def test_the_link_check_catches_a_link_out_of_the_repository_and_a_missing_file() -> None:
    assert link_problem(README, "../elsewhere/spec.md") == "points outside the repository"
    assert link_problem(README, "docs/no-such-page.md") == "no such file"
    assert link_problem(README, "docs/mqtt.md#no-such-heading") is not None
    assert link_problem(README, "docs/mqtt.md") is None


def test_readme_is_a_short_guide_that_starts_a_fresh_machine() -> None:
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= README_MAX_LINES
    assert "make demo" in text and "make test" in text


@pytest.mark.parametrize("doc", USER_DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_user_docs_name_no_commit_hash_and_no_issue_number(doc: Path) -> None:
    text = UUID.sub("", doc.read_text(encoding="utf-8"))
    assert COMMIT_HASH.findall(text) == []
    assert ISSUE_REF.findall(text) == []


def test_no_file_in_the_repository_refers_to_specs_outside_it() -> None:
    offenders = [
        str(path.relative_to(ROOT))
        for path in ROOT.rglob("*")
        if path.is_file()
        and not SKIPPED_DIRS.intersection(path.relative_to(ROOT).parts)
        and not any(part.endswith(".egg-info") for part in path.relative_to(ROOT).parts)
        and OUTSIDE_SPEC.search(path.read_bytes().decode("utf-8", "replace"))
    ]
    assert offenders == []
