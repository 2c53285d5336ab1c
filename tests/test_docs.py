"""The documentation builds without a warning, and its code runs as printed.

- ``sphinx-build -W`` over docs/ (the Markdown pages and the API reference from the docstrings); the reference
  documents each object once.
- Each page of docs/ and README.md runs as a reader would follow it: block after block in page order, in a fresh
  interpreter and a fresh working directory per page. Its ```` ```python ```` blocks run in one namespace; a
  ```` ```{code-block} ```` with a ``:caption:`` is a file, written under that name when the page reaches it (so a
  step that reads a file the page defines later fails). A traceback names the page's line. A block right after a
  ``% not run: <why>`` comment line is skipped (a cluster, or minutes of fitting); keep those few. A page with a
  ``% requires: MODULE`` line skips where that optional module is not installed (torch, ray).
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


def code(text: str) -> list[tuple[str, int, str, str]]:
    """The page's files and Python blocks in page order: ``(kind, line, name, source)``, kind ``"file"`` or
    ``"python"``, line the 1-based page line of the block's first body line, name a file's caption ("" for Python)."""
    steps = []
    for m in FENCE.finditer(text):
        info, indent = m["info"].strip(), len(m["indent"])
        body = "".join(line[indent:] for line in m["body"].splitlines(keepends=True))  # a block inside a list item
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        line = text[: m.start()].count("\n") + 2
        if info.startswith("{code-block}"):
            cap = CAPTION.search(body)
            if cap:
                rest = re.sub(r"^(:\w[\w-]*:.*\n)*", "", body[cap.end():])  # further options
                steps.append(("file", line, cap["name"], rest.lstrip("\n")))
            continue
        if info == "python" and not before.startswith("% not run"):
            steps.append(("python", line, "", body))
    return steps


def script(text: str, steps: list[tuple[str, int, str, str]]) -> str:
    """One script whose lines are the page's lines (other lines left blank): a traceback names the page's line, and
    Warp finds the source of a kernel defined in a block. A file is one statement on its block's opening fence line,
    writing it there."""
    lines = [""] * (text.count("\n") + 1)
    for kind, line, name, source in steps:
        if kind == "file":
            lines[line - 2] = (f"(_p := __import__('pathlib').Path({name!r})).parent.mkdir(parents=True, "
                               f"exist_ok=True); _p.write_text({source!r})")
        else:
            for i, code_line in enumerate(source.splitlines()):
                lines[line - 1 + i] = code_line
    return "\n".join(lines) + "\n"


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


@pytest.fixture(scope="module")
def html(tmp_path_factory) -> Path:
    """The HTML site, built once with ``sphinx-build -W``."""
    out = tmp_path_factory.mktemp("html")
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS),
                           str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"sphinx-build -W failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return out


def test_docs_build(html):
    assert (html / "api" / "warpcloth.html").is_file()


def test_api_reference_documents_each_object_once(html):
    """No class, function or exception has two entries in the reference (a name re-exported by a second module is
    documented under one of them). Sphinx's inventory also lists a class's canonical name (the module that defines
    it), at the same anchor: one entry."""
    import importlib
    import posixpath

    from sphinx.util.inventory import InventoryFile

    with open(html / "objects.inv", "rb") as f:
        inventory = InventoryFile.load(f, "", posixpath.join)
    anchors: dict[int, set[tuple[str, str]]] = {}
    for kind in ("py:class", "py:function", "py:exception"):
        for name, item in inventory.get(kind, {}).items():
            module, _, attr = name.rpartition(".")
            obj = getattr(importlib.import_module(module), attr)
            anchors.setdefault(id(obj), set()).add((item.uri, name))
    twice = sorted(sorted(name for _, name in entries) for entries in anchors.values()
                   if len({uri for uri, _ in entries}) > 1)
    assert not twice, f"documented more than once: {twice}"


@pytest.mark.parametrize("page", pages(), ids=_ids(pages()))
def test_code_blocks_run(page, tmp_path):
    text = page.read_text()
    steps = code(text)
    if not any(kind == "python" for kind, *_ in steps):
        pytest.skip("no Python blocks")
    for module in re.findall(r"^% requires: ([\w.]+)", text, re.M):
        pytest.importorskip(module, reason=f"{page.name} needs {module}")
    path = tmp_path / (page.relative_to(ROOT).as_posix().replace("/", "__").removesuffix(".md") + ".py")
    path.write_text(script(text, steps))
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, path.name], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env=env)
    assert proc.returncode == 0, f"a code block of {page.relative_to(ROOT)} failed:\n{proc.stderr[-4000:]}"


def test_a_file_is_written_where_the_page_reaches_it(tmp_path):
    """A block that reads a file the page defines only further down fails, as it would for a reader."""
    read = "```python\nprint(open('a.txt').read())\n```\n"
    define = "```{code-block} text\n:caption: a.txt\n\nhello\n```\n"
    path = tmp_path / "page.py"
    for page in (read + "\n" + define, define + "\n" + read):
        path.write_text(script(page, code(page)))
        proc = subprocess.run([sys.executable, path.name], cwd=tmp_path, capture_output=True, text=True, timeout=60)
        if page.startswith(read):
            assert proc.returncode != 0 and "FileNotFoundError" in proc.stderr and "line 2" in proc.stderr
    assert proc.returncode == 0 and proc.stdout == "hello\n\n", proc.stderr  # print adds a newline


def test_readme_quick_start_is_tested():
    """The README's quick start is among the blocks run above, and the docs' getting-started page shows it."""
    steps = code((ROOT / "README.md").read_text())
    assert any(kind == "python" and "tape.backward(loss)" in source for kind, _, _, source in steps)
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
