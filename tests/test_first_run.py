"""A new user's first ten minutes: the version, ``python -m warpcloth``, importing from the checkout's root, the
preview picture; and the house: warpcloth.model never imports warpcloth.obstacles."""

import ast
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

import warpcloth as wc
from warpcloth.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _site_env() -> dict:
    """The environment of a Python started with -S (no site: no .pth files, so no editable-install finder) that still
    finds the dependencies: this interpreter's site-packages on PYTHONPATH, after the script's own directory."""
    paths = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), "PYTHONNOUSERSITE": "1"}


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-S", "-c", code], cwd=cwd, env=_site_env(), capture_output=True,
                          text=True, timeout=300)


IMPORT = """\
import sys
import warpcloth, warpcloth.kernels
from warpcloth.kernels.obstacle import obstacle_kernels
assert not [m for m in sys.modules if m.startswith("__editable__")], "an editable install's finder was used"
print(warpcloth.__file__)
print(warpcloth.kernels.__file__)
print(sys.modules["warpcloth.kernels.obstacle"].__file__)
"""


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"warpcloth {wc.__version__}"
    from importlib.metadata import version

    assert wc.__version__ == version("warpcloth")


def test_python_m_warpcloth():
    run = subprocess.run([sys.executable, "-m", "warpcloth", "--help"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("usage: warpcloth") and "simulate" in run.stdout and "--version" in run.stdout
    run = subprocess.run([sys.executable, "-m", "warpcloth", "--version"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.strip() == f"warpcloth {wc.__version__}"


def test_import_from_the_checkouts_root():
    """As after a non-editable ``pip install .``: the root's ./warpcloth comes first on sys.path and shadows the
    installed package, and no editable finder maps warpcloth.kernels; the sibling kernels/ is found."""
    run = _python(IMPORT, ROOT)
    assert run.returncode == 0, run.stderr
    package, kernels, obstacle = run.stdout.split()
    assert Path(package) == ROOT / "warpcloth" / "__init__.py"
    assert Path(kernels) == ROOT / "kernels" / "__init__.py"
    assert Path(obstacle) == ROOT / "kernels" / "obstacle.py"


def test_import_of_the_installed_layout(tmp_path):
    """In the wheel's layout (kernels/ inside the package) the package's own kernels are used, not a sibling's."""
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(ROOT / "warpcloth", tmp_path / "site" / "warpcloth", ignore=ignore)
    shutil.copytree(ROOT / "kernels", tmp_path / "site" / "warpcloth" / "kernels", ignore=ignore)
    shutil.copytree(ROOT / "kernels", tmp_path / "site" / "kernels", ignore=ignore)  # a decoy the package must not use
    run = _python(IMPORT, tmp_path / "site")
    assert run.returncode == 0, run.stderr
    package, kernels, obstacle = run.stdout.split()
    assert Path(kernels) == tmp_path / "site" / "warpcloth" / "kernels" / "__init__.py"
    assert Path(obstacle) == tmp_path / "site" / "warpcloth" / "kernels" / "obstacle.py"


def _imports(path: Path) -> set[str]:
    """Every module a source file names in an import statement, wherever it stands (top level, a function, a
    TYPE_CHECKING block)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def _source(module: str) -> Path | None:
    parts = module.split(".")
    if parts[0] != "warpcloth":
        return None
    base = ROOT / ("kernels" if parts[1:2] == ["kernels"] else "warpcloth")
    rest = parts[2:] if parts[1:2] == ["kernels"] else parts[1:]
    for candidate in (base.joinpath(*rest).with_suffix(".py"), base.joinpath(*rest, "__init__.py")):
        if rest and candidate.is_file():
            return candidate
    return None


def test_model_does_not_import_obstacles():
    """One direction: warpcloth.obstacles builds on warpcloth.model; nothing model imports leads back to obstacles."""
    assert "warpcloth.model" in _imports(ROOT / "warpcloth" / "obstacles.py")
    seen, todo = set(), ["warpcloth.model"]
    while todo:
        module = todo.pop()
        source = _source(module)
        if module in seen or source is None:
            continue
        seen.add(module)
        todo.extend(_imports(source))
    assert "warpcloth.model" in seen and "warpcloth.geometry.motion" in seen
    assert "warpcloth.obstacles" not in seen
