"""The documentation points only at files this repository has, and its user pages say what holds
now: dated runs belong to the experiment log, docs/log/ (docs/index.md).

Three checks, each listing every offender as `file:line: what`:

* a markdown link `[text](path)` in README.md, docs/**/*.md or leaderboard/README.md names a
  relative path that exists (web links and pure `#anchor`s are not checked; `#anchor` parts are
  cut off);
* a tracked text file (.py, .md, .toml, .sh, .txt) names a `*.md` document only if the repository
  has it, relative to the repository root or to the file's folder (`../docs/x.md` in code that
  writes a page one folder down counts as docs/x.md);
* a user page (README.md, docs/*.md; not docs/log/) carries no ISO date (20YY-MM-DD).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: `[text](target)` and `![alt](target)`, an optional "title" after the target.
LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
#: Fenced code blocks and inline code spans: what they hold is not a link.
CODE = re.compile(r"^(```|~~~).*?^\1[^\n]*$|`[^`\n]*`", re.S | re.M)
#: A document's name: word characters, dots, slashes and dashes ending in `.md`, not part of a URL
#: (`https://host/x.md`: nothing may start right after a `:` or inside a longer path).
MD_NAME = re.compile(r"(?<![\w./:-])([\w./-]*\w\.md)\b")
#: An ISO date, the mark of a dated run.
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")

TEXT_SUFFIXES = {".py", ".md", ".toml", ".sh", ".txt"}


def _tracked() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked files are unknown")
    return [f for f in out.stdout.split("\0") if f]


def _line(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def _blank_code(text: str) -> str:
    """`text` with code blocks and spans blanked out, newlines kept (so line numbers hold)."""
    return CODE.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)


def _markdown_pages() -> list[Path]:
    pages = [ROOT / "README.md", ROOT / "leaderboard" / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return [p for p in pages if p.is_file()]


def _user_pages() -> list[Path]:
    return [p for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))] if p.is_file()]


def broken_links(pages: list[Path], root: Path = ROOT) -> list[str]:
    """`file:line: target` for every relative link of `pages` whose path does not exist."""
    bad = []
    for page in pages:
        text = _blank_code(page.read_text(encoding="utf-8"))
        for m in LINK.finditer(text):
            target = m.group(1)
            if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
                continue  # http(s), mailto, ...; an anchor on this page
            path = unquote(target.split("#", 1)[0].split("?", 1)[0])
            if not (page.parent / path).exists():
                bad.append(f"{page.relative_to(root)}:{_line(text, m.start())}: {target}")
    return bad


def missing_documents(files: list[str], root: Path = ROOT) -> list[str]:
    """`file:line: name` for every `*.md` name in `files` (relative to `root`) that is neither at
    `root` (leading `../` dropped) nor beside the file."""
    bad = []
    for rel in files:
        path = root / rel
        if path.suffix not in TEXT_SUFFIXES or not path.is_file():
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        if ".md" not in text:
            continue
        for m in MD_NAME.finditer(text):
            name = m.group(1)
            # `../docs/x.md` in code that writes a page one folder down (leaderboard/README.md)
            # names the repository's docs/x.md.
            up = re.sub(r"^(\.\.?/)+", "", name)
            if not ((root / name).exists() or (path.parent / name).exists() or (root / up).exists()):
                bad.append(f"{rel}:{_line(text, m.start())}: {name}")
    return bad


def dated_lines(pages: list[Path], root: Path = ROOT) -> list[str]:
    """`file:line: date` for every ISO date on `pages`."""
    bad = []
    for page in pages:
        text = page.read_text(encoding="utf-8")
        bad += [f"{page.relative_to(root)}:{_line(text, m.start())}: {m.group(0)}" for m in DATE.finditer(text)]
    return bad


def test_markdown_links_point_at_files_that_exist():
    bad = broken_links(_markdown_pages())
    assert not bad, "links to files this repository does not have:\n" + "\n".join(bad)


def test_every_cited_markdown_document_is_in_the_repository():
    this = Path(__file__).resolve().relative_to(ROOT).as_posix()  # its made-up names are examples
    bad = missing_documents([f for f in _tracked() if f != this])
    assert not bad, "documents cited but not in the repository:\n" + "\n".join(bad)


def test_user_pages_carry_no_dated_runs():
    bad = dated_lines(_user_pages())
    assert not bad, ("dates on user pages (dated runs belong to the experiment log, docs/log/):\n"
                     + "\n".join(bad))


# The checks themselves, on made-up files: each finds what it is for and nothing else.

def test_the_link_check_finds_broken_links_only(tmp_path):
    (tmp_path / "there.md").write_text("x")
    (tmp_path / "sub").mkdir()
    page = tmp_path / "page.md"
    page.write_text("[ok](there.md#part) [dir](sub/) [web](https://example.org/x.md) [anchor](#a)\n"
                    "`[code](nowhere.md)`\n```\n[block](nowhere.md)\n```\n"
                    "![img](gone.png) and [gone](gone.md#part)\n")
    assert broken_links([page], tmp_path) == ["page.md:6: gone.png", "page.md:6: gone.md#part"]


def test_the_citation_check_finds_missing_documents_only(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "formats.md").write_text("x")
    (tmp_path / "README.md").write_text("x")
    (tmp_path / "docs" / "probe.py").write_text(
        '"""docs/formats.md, formats.md (beside it), README.md (at the root), ../docs/formats.md,\n'
        'https://example.org/a/ELSEWHERE.md, GONE.md and ../GONE.md."""\n')
    (tmp_path / "data.json").write_text('"GONE.md"')  # not a text file the check reads
    assert missing_documents(["docs/probe.py", "data.json"], tmp_path) == ["docs/probe.py:2: GONE.md",
                                                                                    "docs/probe.py:2: ../GONE.md"]


def test_the_date_check_finds_dates_only(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("about 20 minutes on 2 CPU cores\nmeasured on 2026-11-27 at load 3\n")
    assert dated_lines([page], tmp_path) == ["page.md:2: 2026-11-27"]
