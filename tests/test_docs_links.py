"""The documentation's relative links lead somewhere: every link from README.md,
CONTRIBUTING.md, docs/*.md and examples/README.md to a file of the repository names a file
that exists, and a link with a #fragment into a Markdown file names one of its headings
(GitHub's anchors: lower case, punctuation dropped, spaces to hyphens, repeats numbered)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted([ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "examples" / "README.md",
                  *(ROOT / "docs").glob("*.md")])
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading's text (without the repeat suffix)."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)      # a link's text only
    text = re.sub(r"[^\w\- ]", "", text.lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor the headings of the Markdown file ``path`` define (code blocks skipped)."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        m = None if fenced else HEADING.match(line)
        if m:
            base = anchor(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    """The link targets of ``path`` outside code blocks."""
    found, fenced = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            found += LINK.findall(re.sub(r"`[^`]*`", "", line))     # not in code spans
    return found


def broken_links(path: Path) -> list[str]:
    """'TARGET: why' for each relative link of ``path`` that leads nowhere."""
    bad = []
    for target in links(path):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):          # http:, https:, mailto:
            continue
        file_part, _, fragment = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            bad.append(f"{target}: no heading with that anchor in {dest.name}")
    return bad


def test_anchor_follows_github():
    assert anchor("Table 2 (`benchmarks/table2.py`)") == "table-2-benchmarkstable2py"
    assert anchor("The hidden-voxel quorum (measured 2026-11-28)") == \
        "the-hidden-voxel-quorum-measured-2026-11-28"
    assert anchor("Blind meshes: all four methods — the CLI's defaults") == \
        "blind-meshes-all-four-methods--the-clis-defaults"


def test_repeated_headings_are_numbered(tmp_path):
    doc = tmp_path / "a.md"
    doc.write_text("# Measured\n\n```\n# not a heading\n```\n## Measured\n")
    assert anchors(doc) == {"measured", "measured-1"}


def test_a_broken_link_is_reported(tmp_path):
    (tmp_path / "b.md").write_text("## Real heading\n")
    doc = tmp_path / "a.md"
    doc.write_text("[ok](b.md#real-heading) [gone](c.md) [bad](b.md#no-such) [web](https://x.org/#y)"
                   " `x[i](j)`\n")
    assert broken_links(doc) == ["c.md: no such file",
                                 "b.md#no-such: no heading with that anchor in b.md"]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    assert broken_links(path) == []
