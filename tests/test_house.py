"""The code keeps to the house rules: docstrings state contracts (a bounded share of the host code), and the code
holds no dates and no issue numbers (those live in the results' provenance lines and the decision log,
docs/decisions.md)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HOST, KERNELS = ROOT / "warpcloth", ROOT / "kernels"

# The share of lines in docstrings (every string-expression statement: module, class, function and attribute
# docstrings) that the host code and the kernels may reach.
MAX_DOCSTRING_SHARE = 0.12

DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
# "issue 37", "issues 37 and 38", "#37": this project's tracker. A citation of another project's bug is written as
# its URL.
ISSUE = re.compile(r"\b[Ii]ssues? #?\d+|(?<![\w/&\"'])#\d{1,4}\b(?![0-9A-Fa-f])")


def docstring_lines(source: str) -> int:
    """Lines of the string-expression statements of a module's source."""
    return sum(node.end_lineno - node.lineno + 1 for node in ast.walk(ast.parse(source))
               if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
               and isinstance(node.value.value, str))


def _files(root: Path, pattern: str) -> list[Path]:
    return sorted(p for p in root.rglob(pattern) if "__pycache__" not in p.parts)


@pytest.mark.parametrize("root", [HOST, KERNELS], ids=["warpcloth", "kernels"])
def test_docstrings_are_a_bounded_share_of_the_code(root):
    counts = [(docstring_lines(p.read_text()), len(p.read_text().splitlines()), p) for p in _files(root, "*.py")]
    docs, lines = sum(c[0] for c in counts), sum(c[1] for c in counts)
    heaviest = ", ".join(f"{p.relative_to(ROOT)} {d}/{n}" for d, n, p in sorted(counts, key=lambda c: -c[0])[:5])
    assert docs <= MAX_DOCSTRING_SHARE * lines, (
        f"{root.name}/: {docs} of {lines} lines are docstrings ({docs / lines:.1%} > {MAX_DOCSTRING_SHARE:.0%}); "
        f"the most: {heaviest}")


def test_docstring_lines_counts_every_string_statement():
    source = '"""one\ntwo"""\nx = 1\n"""attribute"""\n\ndef f():\n    """f."""\n    return "not a statement"\n'
    assert docstring_lines(source) == 4


@pytest.mark.parametrize("root", [HOST, KERNELS], ids=["warpcloth", "kernels"])
def test_the_code_holds_no_dates_and_no_issue_numbers(root):
    found = []
    for path in _files(root, "*"):
        if path.suffix not in (".py", ".toml"):
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            for pattern in (DATE, ISSUE):
                match = pattern.search(line)
                if match:
                    found.append(f"{path.relative_to(ROOT)}:{number}: {match[0]!r}")
    assert not found, "dates or issue numbers in the code:\n" + "\n".join(found)


@pytest.mark.parametrize("text, hits", [
    ("measured 2026-11-27", True), ("(issue 37)", True), ("issue #37", True), ("see #12", True),
    ("color '#1f77b4'", False), ("x[#]", False), ("https://github.com/NVIDIA/warp/issues/1373", False),
    ("tissue 3", False),
])
def test_the_patterns_find_what_they_should(text, hits):
    assert bool(DATE.search(text) or ISSUE.search(text)) == hits, text


POINTER = re.compile(r"decisions\.md,?\s+(?:section\s+)?([\"'])(.+?)\1")


def test_every_pointer_into_the_decision_log_names_one_of_its_sections():
    headings = {" ".join(h.split()) for h in re.findall(r"^#{2,4} (.+)$", (ROOT / "docs" / "decisions.md").read_text(),
                                                         re.M)}
    missing = []
    for path in [*_files(HOST, "*.py"), *_files(KERNELS, "*.py"), *_files(ROOT / "docs", "*.md")]:
        if "_build" in path.parts or path.name == "decisions.md":
            continue
        text = re.sub(r"\n\s*(#\s*)?", " ", path.read_text())  # a title wrapped over lines, in a comment too
        for _, title in POINTER.findall(text):
            if " ".join(title.split()) not in headings:
                missing.append(f"{path.relative_to(ROOT)}: {title!r}")
    assert not missing, "pointers to no section of docs/decisions.md:\n" + "\n".join(missing)
