"""The documents as a test: what a user reads names no development history and links only
files that exist, the results documents open with today's numbers (each with its command, date
and commit), the architecture names every folder of the product, and no comment or docstring
points at a file that is not there. Checked on the files, so a move that forgets the documents
fails here, not in a reader's hands."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("capture_agent", "calibration", "protocol", "reconstructor", "sim")
SCANNED = (*PACKAGES, "bench", "tests")
USER_DOCS = ("README.md", "EVALUATION.md", "BENCHMARKS.md", "RELIABILITY.md")

# A development session or an issue number means nothing to a user; dates and commits do.
HISTORY_WORDS = re.compile(r"\b(session|issue) [0-9]+", re.IGNORECASE)

# A repository path in prose: folders joined by "/", ending in a file with a known suffix or in
# "/" (a folder); or a top-level document such as BENCHMARKS.md. Not preceded by a path or URL
# character, so /tmp/x.py, https://host/a.py and out/eval/EVALUATION.md are not taken apart.
_SUFFIXES = "py|md|toml|sh|json|png|jpg|csv|txt|yaml|yml|service|npz|ply|h5|log"
PATH_TOKEN = re.compile(
    r"(?<![\w./:~$*<{-])"
    r"((?:[A-Za-z_][\w.-]*/)+(?:[\w-]+(?:\.[\w-]+)*\.(?:" + _SUFFIXES + r")\b)?"
    r"|\b[A-Z][A-Z_]+\.md\b)"
    r"(?![\w*<>{}-])"
)


def _user_documents() -> list[Path]:
    docs = [ROOT / name for name in USER_DOCS]
    return docs + sorted((ROOT / "docs").rglob("*.md"))


def _python_files() -> Iterator[Path]:
    for base in SCANNED:
        for path in sorted((ROOT / base).rglob("*.py")):
            if "__pycache__" not in path.parts:
                yield path


def _python_folders() -> set[str]:
    return {p.parent.relative_to(ROOT).as_posix() for p in _python_files()}


def _comments_and_docstrings(path: Path) -> Iterator[tuple[int, str]]:
    """(first line, text) of every comment and every module, class and function docstring."""
    source = path.read_text(encoding="utf-8")
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    yield body[0].lineno, body[0].value.value


def _repository_roots() -> set[str]:
    """The names a repository path may start with: the top level and every product folder's
    own name (a reconstructor module may name a sibling stage's file from its stage folder)."""
    names = {p.name for p in ROOT.iterdir() if not p.name.startswith(".")}
    return names | {Path(folder).name for folder in _python_folders()}


def _broken_paths(path: Path, text: str, roots: set[str]) -> Iterator[tuple[int, str]]:
    """(line offset in text, token) of each repository path in text that does not exist, from
    the root or from the file's own folder or one above it (a module of reconstructor/depth/
    may name the refiner's module from reconstructor/, as the stage folders' docstrings do)."""
    bases = [ROOT, *(p for p in path.parents if p.is_relative_to(ROOT))]
    for match in PATH_TOKEN.finditer(text):
        token = match.group(1)
        if "/" in token and token.split("/", 1)[0] not in roots:
            continue  # not a repository path (out/eval/, OUT/jobs/, src/lerobot/...)
        if not any((base / token).exists() for base in bases):
            yield text.count("\n", 0, match.start()), token


def test_user_documents_name_no_development_sessions_or_issues():
    found = []
    for doc in _user_documents():
        for number, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            if HISTORY_WORDS.search(line):
                found.append(f"{doc.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "say a date or a commit instead:\n" + "\n".join(found)


def test_every_link_and_picture_of_a_user_document_exists():
    """A Markdown link or picture that is not a URL or an anchor names a file beside the
    document (docs/history/ links its pictures as ../evaluation/...)."""
    missing = []
    for doc in _user_documents():
        for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:|#", target):
                continue
            if not (doc.parent / target.split("#")[0]).exists():
                missing.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not missing, "no such file:\n" + "\n".join(missing)


def test_results_documents_open_with_todays_numbers_each_with_command_date_and_commit():
    """EVALUATION.md and BENCHMARKS.md lead with one table of current results; a reader can make
    every row again (its command) and knows what it was measured on (its date and commit)."""
    for name in ("EVALUATION.md", "BENCHMARKS.md"):
        text = (ROOT / name).read_text(encoding="utf-8")
        first = re.search(r"^## (.+)$", text, re.MULTILINE)
        assert first and first.group(1) == "Today's results", f"{name} opens with {first}"
        section = text[first.end() :].split("\n## ", 1)[0]
        rows = [
            r for r in section.splitlines() if r.startswith("| ") and not r.startswith("| result")
        ]
        assert len(rows) >= 5, f"{name}: too few rows in Today's results"
        for row in rows:
            cells = [c.strip() for c in row.strip("|").split("|")]
            command, date, commit = cells[-3:]
            assert command == "the same" or "`" in command, f"{name}: no command in {row[:80]}"
            assert re.search(r"\b20\d\d-\d\d-\d\d\b", date), f"{name}: no date in {row[:80]}"
            assert re.fullmatch(r"[0-9a-f]{7,40}(, [0-9a-f]{7,40})*", commit), f"{name}: {commit!r}"


def test_architecture_names_every_folder_of_the_product():
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = sorted(f for f in _python_folders() if f"{f}/" not in text)
    assert not missing, "add these folders to docs/architecture.md:\n" + "\n".join(missing)


def test_comments_and_docstrings_name_only_files_that_exist():
    roots = _repository_roots()
    broken = []
    for path in _python_files():
        for line, text in _comments_and_docstrings(path):
            for offset, token in _broken_paths(path, text, roots):
                broken.append(f"{path.relative_to(ROOT)}:{line + offset}: {token}")
    assert not broken, "no such file or folder:\n" + "\n".join(sorted(set(broken)))


def test_the_path_pattern_takes_repository_paths_and_leaves_the_rest():
    text = (
        "see capture_agent/recorder/start.py, docs/x.md, BENCHMARKS.md and protocol/formats/; "
        "not /tmp/warm/a.py, https://github.com/a/b.py, out/eval/EVALUATION.md or bench.py"
    )
    tokens = [m.group(1) for m in PATH_TOKEN.finditer(text)]
    assert tokens == [
        "capture_agent/recorder/start.py", "docs/x.md", "BENCHMARKS.md", "protocol/formats/",
        "out/eval/EVALUATION.md",
    ]  # fmt: skip
    roots = {"capture_agent", "docs", "protocol"}  # out/ is not one: an output folder
    assert list(_broken_paths(ROOT / "tests" / "x.py", text, roots)) == [(0, "docs/x.md")]


# RELIABILITY.md: "Files:" maps a letter to a test file, and each row names `letter::test_name`.
_RELIABILITY_FILE = re.compile(r"`(tests/[\w/]+\.py)` \(([A-Z]{1,2})\)")
_RELIABILITY_TEST = re.compile(r"\b([A-Z]{1,2})::(test_\w+)")


def test_every_reliability_row_names_a_test_that_exists():
    """A guarantee is only as good as the test that shows it: each `X::test_name` of
    RELIABILITY.md is a test function of the file its letter names."""
    text = (ROOT / "RELIABILITY.md").read_text(encoding="utf-8")
    files = {letter: ROOT / path for path, letter in _RELIABILITY_FILE.findall(text)}
    missing_files = sorted(str(p.relative_to(ROOT)) for p in files.values() if not p.is_file())
    assert not missing_files, f"RELIABILITY.md names test files that do not exist: {missing_files}"
    defined = {
        letter: {
            n.name for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.FunctionDef)
        }
        for letter, path in files.items()
    }
    named = _RELIABILITY_TEST.findall(text)
    assert len(named) > 50  # the table is read
    broken = sorted(
        {f"{letter}::{name}" for letter, name in named if name not in defined.get(letter, set())}
    )
    assert not broken, "RELIABILITY.md names tests that do not exist:\n" + "\n".join(broken)
