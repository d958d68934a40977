"""Citations of the project's own documents resolve, and nothing cites documents outside the repository.

A citation is a ``docs/….md`` path in a ``.py``, ``.md``, ``.yaml`` or ``.sh`` file of the
repository, optionally followed by section numbers (``docs/environment.md §3``, also as a list:
``§3 object variant, §4, §5``) or by a quoted heading (``docs/method.md "Modes"``). It resolves
when the file exists and, for a section, when the document has a heading numbered ``N.`` (or
``§N``) or a heading with that exact text (its ``N.`` prefix, if any, left out). The seed
documents the project started from live outside the repository, so no file may cite them.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

from conftest import REPO_ROOT

SCANNED_SUFFIXES = (".py", ".md", ".yaml", ".sh")
#: Directories never scanned when git cannot list the files (build outputs, caches, runs).
SKIPPED_DIRS = {"out", "build", "dist", "node_modules", "__pycache__"}
#: Names of the seed documents (and their folder), written in pieces so that this file does not
#: cite them itself.
SEED_DOCUMENTS = ("RL_" "SPEC", "METHOD" ".md", "DEVICE" ".md", "ARCHITECTURE" ".md", "STYLE" ".md",
                  "seed-" "paper", "shared/" "docs")
#: This file's own examples are not citations.
THIS_FILE = Path(__file__).resolve()

_PATH = r"(?<![\w/.-])docs/(?:[\w-]+/)*[\w.-]+\.md"
_SECTION = r"§[ \t]?\d+"
CITATION = re.compile(
    rf"(?P<path>{_PATH})"
    rf"(?:[ \t]+\"(?P<title>[^\"\n]+)\"|(?P<sections>[ \t]*{_SECTION}(?:[^§()\n\"]{{0,30}}?,[ \t]*{_SECTION})*))?")
NUMBERED_HEADING = re.compile(r"^(?:§[ \t]*)?(\d+)\.?(?:[ \t]+(.*))?$")


@dataclass(frozen=True)
class Citation:
    where: str  # "file:line"
    document: str  # "docs/….md", relative to the repository root
    section: str | None  # "§3", '"Modes"' or None (the document alone)


def citations(text: str, where: str) -> list[Citation]:
    """Every citation of a ``docs/….md`` document in ``text`` (``where`` names its file)."""
    out = []
    for number, line in enumerate(text.splitlines(), start=1):
        for m in CITATION.finditer(line):
            at = f"{where}:{number}"
            if m["title"] is not None:
                out.append(Citation(at, m["path"], f'"{m["title"]}"'))
            elif m["sections"]:
                out += [Citation(at, m["path"], f"§{n}") for n in re.findall(r"§[ \t]?(\d+)", m["sections"])]
            else:
                out.append(Citation(at, m["path"], None))
    return out


def headings(markdown: str) -> tuple[set[str], set[str]]:
    """(section numbers, heading texts) of a Markdown document; fenced code blocks are skipped.
    A numbered heading ``## 3. Observations`` gives the number "3" and both "3. Observations"
    and "Observations" as texts."""
    numbers, texts = set(), set()
    fenced = False
    for line in markdown.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            continue
        m = re.match(r"^#{1,6}[ \t]+(.+?)[ \t#]*$", line)
        if fenced or not m:
            continue
        text = m[1]
        texts.add(text)
        numbered = NUMBERED_HEADING.match(text)
        if numbered:
            numbers.add(numbered[1])
            if numbered[2]:
                texts.add(numbered[2].strip())
    return numbers, texts


def unresolved(cited: list[Citation], root: Path) -> list[str]:
    """A message for every citation whose document or section does not exist under ``root``."""
    problems, parsed = [], {}
    for c in cited:
        path = root / c.document
        if not path.is_file():
            problems.append(f"{c.where}: cites {c.document}, which does not exist")
            continue
        if c.section is None:
            continue
        if c.document not in parsed:
            parsed[c.document] = headings(path.read_text(encoding="utf-8"))
        numbers, texts = parsed[c.document]
        found = c.section[1:] in numbers if c.section.startswith("§") else c.section.strip('"') in texts
        if not found:
            problems.append(f"{c.where}: cites {c.document} {c.section}, which is not a heading of it")
    return problems


def repository_files() -> list[Path]:
    """The repository's scanned files: tracked and untracked-but-not-ignored (git), else a walk
    that skips hidden, build and run folders."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                                cwd=REPO_ROOT, capture_output=True, check=True).stdout.decode().split("\0")
        files = [REPO_ROOT / name for name in listed if name]
    except (OSError, subprocess.CalledProcessError):
        files = [p for p in REPO_ROOT.rglob("*")
                 if not any(part.startswith(".") or part in SKIPPED_DIRS or part.endswith(".egg-info")
                            for part in p.relative_to(REPO_ROOT).parts[:-1])]
    return sorted(p for p in files
                  if p.suffix in SCANNED_SUFFIXES and p.is_file() and p.resolve() != THIS_FILE)


def repository_citations() -> list[Citation]:
    out = []
    for path in repository_files():
        out += citations(path.read_text(encoding="utf-8", errors="replace"), str(path.relative_to(REPO_ROOT)))
    return out


# ------------------------------------------------------------------ the checker on examples


def _docs(tmp_path: Path, **documents: str) -> Path:
    (tmp_path / "docs").mkdir()
    for name, text in documents.items():
        (tmp_path / "docs" / f"{name}.md").write_text(text, encoding="utf-8")
    return tmp_path


SPEC = "# Spec\n\n## 1. Robot\n\n### Timing\n\n## 2. Reference motion\n\n```bash\n# 7. not a heading\n```\n"
GUIDE = "# Guide\n\n## Modes\n\n## Our choices\n"


def test_sections_and_headings_that_exist_resolve(tmp_path):
    root = _docs(tmp_path, spec=SPEC, guide=GUIDE)
    text = 'a (docs/spec.md §1, §2) b docs/spec.md "Timing" c docs/guide.md "Modes" d docs/spec.md\n'
    cited = citations(text, "x.py")
    assert len(cited) == 5
    assert unresolved(cited, root) == []


def test_a_numbered_heading_is_also_cited_by_its_text(tmp_path):
    root = _docs(tmp_path, spec=SPEC)
    assert unresolved(citations('docs/spec.md "Reference motion"', "x.py"), root) == []


def test_a_missing_document_is_reported_with_file_and_line(tmp_path):
    root = _docs(tmp_path, spec=SPEC)
    assert unresolved(citations("ok\nsee docs/nowhere.md §1\n", "x.py"), root) == [
        "x.py:2: cites docs/nowhere.md, which does not exist"]


def test_a_missing_section_number_is_reported(tmp_path):
    root = _docs(tmp_path, spec=SPEC)
    assert unresolved(citations("(docs/spec.md §3)", "x.yaml"), root) == [
        "x.yaml:1: cites docs/spec.md §3, which is not a heading of it"]


def test_every_section_of_a_list_is_checked(tmp_path):
    root = _docs(tmp_path, spec=SPEC)
    assert unresolved(citations("(docs/spec.md §1 object variant, §2 terms, §9)", "x.py"), root) == [
        "x.py:1: cites docs/spec.md §9, which is not a heading of it"]


def test_a_missing_heading_is_reported(tmp_path):
    root = _docs(tmp_path, guide=GUIDE)
    assert unresolved(citations('docs/guide.md "Interaction residuals"', "x.md"), root) == [
        'x.md:1: cites docs/guide.md "Interaction residuals", which is not a heading of it']


def test_a_comment_line_inside_a_code_block_is_not_a_heading(tmp_path):
    root = _docs(tmp_path, spec=SPEC)
    assert len(unresolved(citations("docs/spec.md §7", "x.py"), root)) == 1


def test_a_path_inside_another_path_is_not_a_citation():
    assert citations("out/docs/run.md and ../docs/x.md", "x.md") == []


# ------------------------------------------------------------------ the repository


def test_the_specs_are_cited_by_section_and_by_heading():
    cited = {(c.document, c.section) for c in repository_citations()}
    assert ("docs/environment.md", "§9") in cited
    assert ("docs/method.md", '"Modes"') in cited


def test_every_citation_of_a_project_document_resolves():
    assert unresolved(repository_citations(), REPO_ROOT) == []


def test_no_file_cites_the_seed_documents():
    found = []
    for path in repository_files():
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
            found += [f"{path.relative_to(REPO_ROOT)}:{number}: {name}" for name in SEED_DOCUMENTS if name in line]
    assert found == []
