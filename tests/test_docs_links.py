"""The documentation's links between its own pages resolve: every ``[text](page.md#anchor)`` names a file
that exists and a heading of it, by GitHub's rule for heading anchors (lower case; letters, digits,
spaces, ``-`` and ``_`` kept, anything else — ``×``, ``–``, ``'`` — dropped; spaces become ``-``; a
repeated heading gets ``-1``, ``-2``, …)."""
from __future__ import annotations

import glob
import os
import re
import unicodedata

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINK = re.compile(r"\]\(([^)#\s]*)#([^)\s]+)\)")


def github_slug(heading: str) -> str:
    kept = (c for c in heading.strip().lower()
            if c in " -_" or unicodedata.category(c)[0] in "LN")
    return "".join(kept).replace(" ", "-")


def anchors(path: str) -> set[str]:
    out, seen, fenced = set(), {}, False
    for line in open(path, encoding="utf-8"):
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"^#{1,6} (.*)", line)
        if m:
            s = github_slug(re.sub(r"`", "", m.group(1)))
            k = seen.get(s, 0)
            seen[s] = k + 1
            out.add(s if k == 0 else f"{s}-{k}")
    return out


def test_slug_rule():
    assert github_slug("The paper lenses' camera maps as 3×16 networks") == "the-paper-lenses-camera-maps-as-316-networks"
    assert github_slug("Second-order training: the Levenberg–Marquardt finish") == \
        "second-order-training-the-levenbergmarquardt-finish"


def test_every_anchor_link_resolves():
    pages = sorted(glob.glob(os.path.join(ROOT, "docs", "*.md"))) + [os.path.join(ROOT, "README.md")]
    known = {}
    broken = []
    for page in pages:
        text = open(page, encoding="utf-8").read()
        for target, anchor in LINK.findall(text):
            if target.startswith(("http://", "https://")):
                continue
            dest = os.path.normpath(os.path.join(os.path.dirname(page), target)) if target else page
            if not dest.endswith(".md"):
                continue
            if not os.path.exists(dest):
                broken.append(f"{os.path.relpath(page, ROOT)}: {target} does not exist")
                continue
            if dest not in known:
                known[dest] = anchors(dest)
            if anchor not in known[dest]:
                broken.append(f"{os.path.relpath(page, ROOT)}: {target or '(same page)'}#{anchor}")
    assert not broken, "links to headings that do not exist:\n" + "\n".join(broken)
