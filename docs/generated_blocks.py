"""Generated blocks of the docs: text between marker comments that a script writes, never a person.

    <!-- generated: NAME (docs/make_performance.py) -->
    ...the generated text...
    <!-- end generated -->

Everything between the two comments is replaced by its generator; the marker lines themselves stay as
written (the part after NAME says who writes the block).  docs/make_performance.py and docs/make_reference.py
fill their blocks with :func:`fill`; tests/test_docs_generated.py reads them back with :func:`blocks`.
"""
from __future__ import annotations

import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

BLOCK = re.compile(r"(<!-- generated: ([\w.-]+)[^>]*-->\n)(.*?)(<!-- end generated -->)", re.S)


def blocks(text: str) -> dict:
    """The generated blocks of a page: {name: text between the markers}."""
    out = {}
    for m in BLOCK.finditer(text):
        if m.group(2) in out:
            raise ValueError(f"generated block {m.group(2)!r} appears twice")
        out[m.group(2)] = m.group(3)
    return out


def fill(text: str, bodies: dict, page: str = "page") -> str:
    """``text`` with each block named in ``bodies`` replaced by its body (a trailing newline is added where
    missing).  Every name must have its markers in ``text``: a block its generator cannot find is an error."""
    missing = set(bodies) - set(blocks(text))
    if missing:
        raise KeyError(f"{page}: no markers for the generated block(s) {', '.join(sorted(missing))}: add "
                       f"'<!-- generated: NAME -->' and '<!-- end generated -->' lines where each goes")

    def sub(m):
        name = m.group(2)
        if name not in bodies:
            return m.group(0)
        body = bodies[name]
        return m.group(1) + (body if body.endswith("\n") else body + "\n") + m.group(4)

    return BLOCK.sub(sub, text)


def normalised(body: str) -> str:
    """A block body as :func:`fill` writes it (with its trailing newline)."""
    return body if body.endswith("\n") else body + "\n"


def write_pages(pages: dict, check: bool = False) -> list:
    """Fill the blocks of each page (``{path relative to the repository: {name: body}}``); with ``check``,
    write nothing and return the pages whose blocks differ.  Returns the pages changed (or that would be)."""
    changed = []
    for rel, bodies in pages.items():
        path = os.path.join(ROOT, rel)
        with open(path, encoding="utf-8") as f:
            old = f.read()
        new = fill(old, bodies, rel)
        if new != old:
            changed.append(rel)
            if not check:
                tmp = path + ".tmp"
                with open(tmp, "w", encoding="utf-8") as f:
                    f.write(new)
                os.replace(tmp, path)
    return changed


def md_cell(text: str) -> str:
    """Text safe inside a markdown table cell: one line, ``|`` escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def table(header: list, rows: list) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(md_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
