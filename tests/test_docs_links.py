"""The documentation's links resolve: every relative ``[text](path)`` or ``![alt](path)`` of README.md and
docs/*.md (docs/performance.md included) names a file that exists, and every ``[text](page.md#anchor)`` a
heading of that page, by GitHub's rule for heading anchors (lower case; letters, digits, spaces, ``-`` and
``_`` kept, anything else — ``×``, ``–``, ``'`` — dropped; spaces become ``-``; a repeated heading gets
``-1``, ``-2``, …).  Links inside code blocks and code spans are not links."""
from __future__ import annotations

import glob
import os
import re
import unicodedata

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINK = re.compile(r"\]\(([^)#\s]*)#([^)\s]+)\)")
TARGET = re.compile(r"\]\(([^)\s]+)\)")
PAGES = sorted(glob.glob(os.path.join(ROOT, "docs", "*.md"))) + [os.path.join(ROOT, "README.md")]


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


def prose(path: str) -> str:
    """The page without its fenced code blocks and code spans (what GitHub renders as links)."""
    text = re.sub(r"^```.*?^```", "", open(path, encoding="utf-8").read(), flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def test_slug_rule():
    assert github_slug("The paper lenses' camera maps as 3×16 networks") == "the-paper-lenses-camera-maps-as-316-networks"
    assert github_slug("Second-order training: the Levenberg–Marquardt finish") == \
        "second-order-training-the-levenbergmarquardt-finish"


def test_the_pages_checked_include_the_front_page_and_the_figures():
    names = {os.path.relpath(p, ROOT) for p in PAGES}
    assert {"README.md", os.path.join("docs", "performance.md")} <= names


def test_every_anchor_link_resolves():
    known = {}
    broken = []
    for page in PAGES:
        for target, anchor in LINK.findall(prose(page)):
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


def test_every_relative_file_link_resolves():
    broken = []
    for page in PAGES:
        for target in TARGET.findall(prose(page)):
            path = target.split("#", 1)[0]
            if not path or re.match(r"^[a-z][a-z0-9+.-]*:", path):      # same-page anchor, http:, mailto:
                continue
            dest = os.path.normpath(os.path.join(os.path.dirname(page), path))
            if not os.path.exists(dest):
                broken.append(f"{os.path.relpath(page, ROOT)}: {target}")
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)


def test_user_docs_do_not_link_into_the_lab():
    """lab/ is kept apart from the product: no user page links into it."""
    offenders = [f"{os.path.relpath(p, ROOT)}: {target}" for p in PAGES for target in TARGET.findall(prose(p))
                 if re.match(r"^(\.\./)*lab(/|$)", target)]
    assert not offenders, "links into lab/:\n" + "\n".join(offenders)
