"""The documentation builds without a warning, and its code runs as printed.

- ``sphinx-build -W`` over docs/ (the Markdown pages and the API reference from the docstrings).
- Every ```` ```python ```` block of README.md and of each page of docs/ runs, in order, in one namespace per page
  (as a reader would paste them into one session), in a fresh working directory; a traceback names the page's line.
  A ```` ```{code-block} ```` with a ``:caption:`` is a file: it is written there under that name first. A block
  right after a ``% not run: <why>`` comment line is skipped (a cluster, or minutes of fitting); keep those few. A
  page with a ``% requires: MODULE`` line skips where that optional module is not installed (torch, ray).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,})(?P<info>[^\n`]*)\n(?P<body>.*?)^(?P=indent)(?P=fence)[ \t]*$",
                   re.S | re.M)
CAPTION = re.compile(r"^:caption:[ \t]*(?P<name>\S+)[ \t]*\n", re.M)


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)]


def code(text: str) -> tuple[list[tuple[str, str]], list[tuple[int, str]]]:
    """The page's files ``(name, content)`` and its Python blocks ``(line, source)``, in order."""
    files, blocks = [], []
    for m in FENCE.finditer(text):
        info, indent = m["info"].strip(), len(m["indent"])
        body = "".join(line[indent:] for line in m["body"].splitlines(keepends=True))  # a block inside a list item
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        line = text[: m.start()].count("\n") + 2
        if info.startswith("{code-block}"):
            cap = CAPTION.search(body)
            if cap:
                rest = re.sub(r"^(:\w[\w-]*:.*\n)*", "", body[cap.end():])  # further options
                files.append((cap["name"], rest.lstrip("\n")))
            continue
        if info == "python" and not before.startswith("% not run"):
            blocks.append((line, body))
    return files, blocks


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


def test_docs_build(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS),
                           str(tmp_path / "html")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"sphinx-build -W failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert (tmp_path / "html" / "api" / "warpcloth.html").is_file()


@pytest.mark.parametrize("page", pages(), ids=_ids(pages()))
def test_code_blocks_run(page, tmp_path):
    text = page.read_text()
    files, blocks = code(text)
    if not blocks:
        pytest.skip("no Python blocks")
    for module in re.findall(r"^% requires: ([\w.]+)", text, re.M):
        pytest.importorskip(module, reason=f"{page.name} needs {module}")
    for name, content in files:
        (tmp_path / name).write_text(content)
    # One script whose lines are the page's lines (other lines left blank): a traceback names the page's line, and
    # Warp finds the source of a kernel defined in a block.
    lines = [""] * (text.count("\n") + 1)
    for line, source in blocks:
        for i, code_line in enumerate(source.splitlines()):
            lines[line - 1 + i] = code_line
    script = tmp_path / (page.relative_to(ROOT).as_posix().replace("/", "__").removesuffix(".md") + ".py")
    script.write_text("\n".join(lines) + "\n")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, script.name], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env=env)
    assert proc.returncode == 0, f"a code block of {page.relative_to(ROOT)} failed:\n{proc.stderr[-4000:]}"


def test_readme_quick_start_is_tested():
    """The README's quick start is among the blocks run above, and the docs' getting-started page shows it."""
    _, blocks = code((ROOT / "README.md").read_text())
    assert any("tape.backward(loss)" in source for _, source in blocks)
    assert "<!-- start: quick start -->" in (DOCS / "getting-started.md").read_text()


def test_ci_runs_the_readme_test_command():
    """CI (.ci/run) installs the extras the README's test command installs and runs its test command exactly."""
    readme = (ROOT / "README.md").read_text()
    command = next(line for line in readme.splitlines() if line.startswith("python3 -m venv") and "pytest" in line)
    install = re.search(r'pip install (-e "\.\[[\w,]+\]")', command)[1]
    test = command.split(install + " && ", 1)[1]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert any(line.startswith("python -m pip install") and line.endswith(install) for line in ci), install
    assert test in ci, f"{test!r} is not a line of .ci/run"


def test_api_reference_lists_the_public_api():
    """Every name of ``warpcloth.__all__`` has its entry in the API reference (docs/api/warpcloth.md)."""
    import warpcloth

    page = (DOCS / "api" / "warpcloth.md").read_text()
    listed = set(re.findall(r"^\.\. auto\w+:: warpcloth\.(\w+)$", page, re.M))
    assert set(warpcloth.__all__) == listed, (f"not in docs/api/warpcloth.md: {sorted(set(warpcloth.__all__) - listed)}"
                                              f"; not public: {sorted(listed - set(warpcloth.__all__))}")
