"""The docs stay navigable and the code stays free of dated figures (issue 43, item 3).

- Every ``docs/<note>.md`` path cited anywhere in the repository (README, docs, code, tests,
  benchmarks, kernels, scene files) exists, and the ``#anchor`` or quoted section name after it
  ("Section" or 'Section') names a heading of that file (a quoted name may be the start of the
  heading; a bold paragraph lead-in ``**Name**`` or the first cell of a table row counts too).
- Every relative Markdown link between docs (``[x](note.md#anchor) "Section"``) resolves the same way.
- Every reference note (``docs/*.md`` but the index ``README.md`` and the figures table
  ``performance.md``) is under ``REFERENCE_NOTE_MAX_BYTES``; results live in ``docs/results/``.
- No date (YYYY-MM-DD) in ``clrecon/``: figures and their dates live in docs/performance.md and
  the results notes, never in code or docstrings.
"""
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REFERENCE_NOTE_MAX_BYTES = 15_000
SUFFIXES = (".py", ".md", ".toml", ".cl", ".h", ".cfg", ".txt", ".sh", ".yml", ".yaml")
#: ``docs/<note>.md``, an optional ``#anchor``, then optionally a quoted section name after a space,
#: a comma or an opening parenthesis; a name not closed on its line is checked as a prefix.
ROOT_CITE = re.compile(r"(?<![\w/.-])docs/([\w./-]+\.md)(#[\w-]+)?"
                       r"(?:`{1,2})?(?:(?:\s*\(\s*|,\s*|\s+)(\\?[\"'])([^\"'\n]*?)(\\?[\"']|$))?", re.M)
REL_LINK = re.compile(r"\]\((?!https?:|#|/|mailto:)([^)\s#]+\.md)(#[^)\s]*)?\)(?:\s*,?\s*\"([^\"\n]+)(\"|$))?", re.M)
DATE = re.compile(r"20[0-9]{2}-[0-9]{2}-[0-9]{2}")


def _files():
    out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.split()
    return [ROOT / f for f in out if f.endswith(SUFFIXES) and (ROOT / f).is_file()]


def _norm(s: str) -> str:
    return re.sub(r"\s+", " ", s.replace("`", "").replace("\\", "")).strip().lower()


def _slug(heading: str) -> str:
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _names(md: Path):
    """(headings, other names: bold lead-ins and first table cells) of a Markdown file."""
    heads, others, fence = [], [], False
    for line in md.read_text().splitlines():
        if line.startswith("```"):
            fence = not fence
            continue
        if fence:
            continue
        if m := re.match(r"#{1,6} (.*)", line):
            heads.append(m.group(1))
        elif m := re.match(r"\s*(?:- |\d+\. )?\*\*(.+?)\*\*", line):
            others.append(m.group(1))
        elif m := re.match(r"\|\s*([^|]+?)\s*\|", line):
            others.append(m.group(1))
    return heads, others


def _check(target: Path, anchor, section, where, closed=True):
    if not target.is_file():
        return [f"{where}: {target.relative_to(ROOT)} does not exist"]
    heads, others = _names(target)
    if anchor and anchor[1:] not in {_slug(h) for h in heads}:
        return [f"{where}: no heading for {anchor} in {target.relative_to(ROOT)}"]
    if section is not None and section.strip():
        s = _norm(section)
        if not closed and len(s) < 3:
            return []
        if not any(_norm(h).startswith(s) for h in heads + others):
            return [f"{where}: no section \"{section}\" in {target.relative_to(ROOT)}"]
    return []


def test_every_cited_docs_path_and_section_exists():
    bad, n = [], 0
    for f in _files():
        text = f.read_text(errors="replace")
        for m in ROOT_CITE.finditer(text):
            where = f"{f.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}"
            quote, section, close = m.group(3), m.group(4), m.group(5)
            bad += _check(ROOT / "docs" / m.group(1), m.group(2), section if quote else None, where,
                          closed=bool(close))
            n += 1
        if f.suffix == ".md":
            for m in REL_LINK.finditer(text):
                where = f"{f.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}"
                target = (f.parent / m.group(1)).resolve()
                bad += _check(target, m.group(2), m.group(3), where, closed=m.group(4) == "\"")
                n += 1
    assert n > 100, f"only {n} citations found: the patterns no longer match the repository's style"
    assert not bad, "\n".join(bad)


def test_reference_notes_are_short_and_results_have_their_folder():
    notes = [p for p in (ROOT / "docs").glob("*.md") if p.name not in ("README.md", "performance.md")]
    assert len(notes) > 10
    big = [f"{p.name}: {p.stat().st_size} bytes" for p in notes if p.stat().st_size >= REFERENCE_NOTE_MAX_BYTES]
    assert not big, f"reference notes over {REFERENCE_NOTE_MAX_BYTES} bytes (move results to docs/results/): {big}"
    assert list((ROOT / "docs" / "results").glob("*.md"))


def test_index_lists_every_note():
    index = (ROOT / "docs" / "README.md").read_text()
    missing = [p.relative_to(ROOT / "docs").as_posix() for p in
               list((ROOT / "docs").glob("*.md")) + list((ROOT / "docs" / "results").glob("*.md"))
               if p.name != "README.md" and f"({p.relative_to(ROOT / 'docs').as_posix()})" not in index]
    assert not missing, f"docs/README.md does not link {missing}"


def test_no_dates_in_the_package():
    hits = []
    for f in sorted((ROOT / "clrecon").rglob("*")):
        if f.is_file() and f.suffix in SUFFIXES + (".json",):
            for i, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
                if DATE.search(line):
                    hits.append(f"{f.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not hits, "dates in clrecon/ (figures and dates belong in docs/performance.md or docs/results/):\n" + \
        "\n".join(hits)
