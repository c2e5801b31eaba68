"""Every reference to a section of a document under docs/ resolves: where a .py, .c, .h or .md file of the repository
names ``docs/<file>.md`` followed by a quoted section title, that file exists and holds a heading containing the title.

Independent of any one document's content: it reads the references where they are written and the headings the named
file holds now, so a section renamed or moved to another file (e.g. docs/wavelet.md's measurement history, moved to
docs/wavelet_kernel_log.md) fails here until its references follow.

The forms in use (looked up before writing this): ``docs/x.md "Title"``, ``docs/x.md, "Title"``, ``docs/x.md ("Title")``,
the title split over lines of a comment or docstring (``#:``, ``#``, `` * `` prefixes are dropped), cut short with
``...`` or ``…`` (the part before it must be in a heading), escaped quotes inside a Python string (``\\"Title\\"``),
typographic quotes. Only the first quoted title after a file name is a reference (``docs/x.md "A" and "B"``: write the
file name before each). A heading is a Markdown ``#`` heading or the bold lead-in that opens a paragraph or list item
(``**Title (date, CPU).**`` — the log's sections are bold lead-ins); the match is case-insensitive and whitespace-
insensitive, and a title may be any part of the heading (the heading's date and CPU need not be repeated).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUFFIXES = {".py", ".c", ".h", ".md"}
SKIP_DIRS = {".venv", ".git", "__pycache__", "node_modules", "build", "dist", "cache", ".pytest_cache", ".ruff_cache"}

# docs/<file>.md, then a comma, a space or " (", then an opening quote (optionally escaped), the title up to the closing one
REF = re.compile(r'docs/([A-Za-z0-9_\-]+\.md)(?:,\s*|\s+\(?|\s*\()\\?["“]([^"”]{1,400}?)\\?["”]')
# a continuation line's comment prefix inside a title that spans lines
CONT = re.compile(r"\s*\n\s*(?:#:?|\*(?!\*)|//)?\s*")
HEADING = re.compile(r"^#{1,6}\s+(.+)$", re.M)
# a bold lead-in: "**" at the start of a line (after indentation and an optional list marker), up to the closing "**"
LEAD_IN = re.compile(r"^[ \t]*(?:[*-][ \t]+)?\*\*(.+?)\*\*", re.M | re.S)


def _norm(text: str) -> str:
    """Whitespace collapsed, case folded, code marks dropped (a docstring may quote `res: auto` as res: auto)."""
    return " ".join(text.replace("`", "").split()).casefold()


def _in(title: str, heading: str) -> bool:
    """The normalised title in the normalised heading, at word boundaries ("Lighting" is not in "Relighting")."""
    return re.search(r"(?<!\w)" + re.escape(title) + r"(?!\w)", heading) is not None


#: References known not to resolve; each must still fail (so a fix removes it from here). None today.
KNOWN_STALE: set[tuple[str, str, str]] = set()


def _sources():
    """The repository's .py/.c/.h/.md files (not this one), the virtual environment, caches and build output pruned."""
    for top, dirs, files in os.walk(ROOT):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info"))
        for name in sorted(files):
            path = Path(top) / name
            if path.suffix in SUFFIXES and name != Path(__file__).name:
                yield path


def references() -> list[tuple[str, int, str, str]]:
    """(source file, line, docs file, title) for every quoted section reference in the repository."""
    out = []
    for path in _sources():
        text = path.read_text(encoding="utf-8", errors="replace")
        if "docs/" not in text:
            continue
        for m in REF.finditer(text):
            title = CONT.sub(" ", m.group(2))
            title = re.split(r"\.\.\.|…", title)[0].strip(" ,;:(")
            if title:
                out.append((str(path.relative_to(ROOT)), text.count("\n", 0, m.start()) + 1, m.group(1), title))
    return out


def headings(doc: Path) -> list[str]:
    """The normalised ``#`` headings and paragraph-opening bold lead-ins of a Markdown file."""
    text = doc.read_text(encoding="utf-8")
    return [_norm(h) for h in HEADING.findall(text)] + [_norm(b) for b in LEAD_IN.findall(text)]


def test_the_scan_finds_the_forms_in_use():
    """The scan is not vacuous: it finds references in every form this repository writes (a guard on the regexes)."""
    refs = references()
    assert len(refs) >= 30
    got = {(f, _norm(t)) for _, _, f, t in refs}
    for f, t in [("wavelet_kernel_log.md", "the tile follows the relighter's threads"),  # plain, in C and Python
                 ("wavelet_kernel_log.md", "the fourth row (small studio, 292 kept) and the call's non-dense parts"),  # over lines
                 ("wavelet_kernel_log.md", "issue 39, grouped sparse blocks"),  # escaped quotes in a Python string
                 ("wavelet.md", "the dense arithmetic"),  # comma form
                 ("wavelet_kernel_log.md", "runs of adjacent dense lines"),  # parenthesis form
                 ("wavelet_kernel_log.md", "the fourth row")]:  # cut short with "..."
        assert (f, t) in got, (f, t)


def test_every_docs_section_reference_names_a_heading_of_that_file():
    bad, stale = [], set()
    for src, line, name, title in references():
        doc = ROOT / "docs" / name
        if not doc.is_file():
            bad.append(f"{src}:{line}: docs/{name} does not exist (section {title!r})")
            continue
        t = _norm(title)
        if not any(_in(t, h) for h in headings(doc)):
            if (src, name, title) in KNOWN_STALE:
                stale.add((src, name, title))
                continue
            bad.append(f"{src}:{line}: docs/{name} has no heading containing {title!r}")
    assert not bad, "section references that do not resolve:\n" + "\n".join(bad)
    assert stale == KNOWN_STALE, f"fixed since (remove from KNOWN_STALE): {sorted(KNOWN_STALE - stale)}"


def test_the_heading_rule_on_a_small_document(tmp_path):
    """The heading rule itself, on a document written here: # headings and bold lead-ins count, bold text inside a
    paragraph does not."""
    doc = tmp_path / "d.md"
    doc.write_text("# Top\n\n## A section (2026)\n\n**A lead-in (Intel Xeon,\nAVX-512).** Text with **inner bold**.\n\n"
                   "* **A bullet lead-in**: text\n  - **An indented one** text\n")
    hs = headings(doc)
    for t in ["top", "a section", "a lead-in (intel xeon, avx-512).", "a bullet lead-in", "an indented one"]:
        assert any(_in(_norm(t), h) for h in hs), t
    assert not any("inner bold" in h for h in hs)
    assert not any(_in("section (20", h) for h in hs) and not any(_in("ullet lead-in", h) for h in hs)
