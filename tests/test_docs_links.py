"""The user docs' relative links and images resolve: README.md, docs/**.md, benchmarks/README.md.

A link is `[text](target)` or `![alt](target)`; web links (scheme://, mailto:) are not followed. A
target's file must exist relative to the Markdown file, and a `#fragment` must name a heading of
the target (GitHub's anchor rule: lower case, punctuation other than `-` and `_` dropped, spaces to
`-`). Paths outside the repository (../shared) are not the docs' to promise, so they fail too.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")


def doc_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "benchmarks" / "README.md"]
    files += sorted((ROOT / "docs").rglob("*.md"))
    return [f for f in files if f.is_file()]


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks (code may hold anything that looks like a link)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line.strip()):
            fenced = not fenced
            continue
        if not fenced:
            out.append(line)
    return out


def anchor(heading: str) -> str:
    """GitHub's anchor for a heading's text."""
    text = re.sub(r"[`*]", "", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in prose_lines(path.read_text(encoding="utf-8")):
        m = re.match(r"^#{1,6}\s+(.*)$", line)
        if not m:
            continue
        base = anchor(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    bad = []
    for line in prose_lines(path.read_text(encoding="utf-8")):
        # Inline code spans are not links.
        for target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):
                continue
            file_part, _, frag = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            try:
                dest.relative_to(root)
            except ValueError:
                bad.append(f"{target} (outside the repository)")
                continue
            if not dest.exists():
                bad.append(f"{target} (no such file)")
            elif frag and dest.suffix == ".md" and frag not in anchors(dest):
                bad.append(f"{target} (no heading #{frag})")
    return bad


def test_anchor_follows_github_rule():
    assert anchor("SPIn-NeRF: the default command beside the naive baseline") == (
        "spin-nerf-the-default-command-beside-the-naive-baseline"
    )
    assert anchor("Background depth D_bg: error against run time (`benchmarks/carve.py --dbg-only`)") == (
        "background-depth-d_bg-error-against-run-time-benchmarkscarvepy---dbg-only"
    )


def test_checker_finds_a_broken_link(tmp_path):
    (tmp_path / "a.md").write_text("# Top\n[ok](a.md#top) [gone](b.png) [bad](a.md#nope) [out](../x.md)\n")
    assert broken_links(tmp_path / "a.md", root=tmp_path) == [
        "b.png (no such file)",
        "a.md#nope (no heading #nope)",
        "../x.md (outside the repository)",
    ]


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_links_and_images_resolve(path):
    assert broken_links(path) == []
