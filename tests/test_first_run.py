"""A new user's first ten minutes: the version, ``python -m warpcloth``, importing from the checkout's root, the
preview picture; and the house: warpcloth.model never imports warpcloth.obstacles."""

import ast
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

import warpcloth as wc
from warpcloth.cli import main
from warpcloth.preview import CLOTH_COLOR, PREVIEW_FRAMES, write_preview

ROOT = Path(__file__).resolve().parents[1]


def _site_env() -> dict:
    """The environment of a Python started with -S (no site: no .pth files, so no editable-install finder) that still
    finds the dependencies: this interpreter's path on PYTHONPATH (after the current directory, which -c puts first),
    less the checkout's root."""
    paths = [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]]
    paths += [p for p in sys.path if p and Path(p).resolve() != ROOT and Path(p).is_dir()]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}


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


# ----------------------------------------------------------------------------------------------------------------------
# The preview: warpcloth.preview.write_preview and warpcloth simulate --preview.

CLOTH_RGB = np.array(CLOTH_COLOR)


def _trajectory(frame_count: int = 50):
    """A 0.5 m sheet falling and swinging past a static box, and a ball-sized box moving along x."""
    mesh = wc.grid_mesh(6, 6, 0.5, 0.5)
    t = np.arange(frame_count)[:, None, None] * 0.02
    frames = mesh.positions[None] + np.array([-0.25, -0.25, 0.6]) + t * np.array([0.3, 0.0, -0.5])
    box_v, box_t = wc.box_mesh((0.3, 0.3, 0.1))
    ball_v, ball_t = wc.box_mesh((0.05, 0.05, 0.05))
    moving = ball_v[None] + t * np.array([1.0, 0.0, 0.0])
    return mesh.triangles, frames, [("floor", box_v, box_t), ("ball", moving, ball_t)]


def _cloth_pixels(rgb: np.ndarray) -> int:
    """How many pixels have the cloth's hue (some shade of it: the lighting scales its colour)."""
    rgb = rgb[..., :3].astype(np.float64) / 255.0
    scale = rgb.max(axis=-1, keepdims=True)
    hue = np.divide(rgb, scale, out=np.zeros_like(rgb), where=scale > 0.1)
    return int(np.sum(np.all(np.abs(hue - CLOTH_RGB / CLOTH_RGB.max()) < 0.12, axis=-1)))


def _gif_frames(path) -> list[np.ndarray]:
    with Image.open(path) as im:
        return [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(im)]


def test_a_long_fall_is_squeezed_not_drawn_as_a_thin_column(tmp_path):
    # a 0.5 m sheet falling 1 m, and 100 m: equal scale on every axis would draw the second 20x smaller; its box is
    # squeezed along z to MAX_ASPECT times its width instead, so the sheet keeps a size one can see
    mesh = wc.grid_mesh(6, 6, 0.5, 0.5)
    counts = []
    for depth in (1.0, 100.0):
        frames = mesh.positions[None] + np.linspace(0.0, 1.0, 10)[:, None, None] * np.array([0.0, 0.0, -depth])
        write_preview(tmp_path / f"fall{depth:g}.gif", triangles=mesh.triangles, frames=frames, fps=10.0, size=3.0)
        counts.append(_cloth_pixels(_gif_frames(tmp_path / f"fall{depth:g}.gif")[0]))
    assert counts[0] > 200 and counts[1] > 0.2 * counts[0], counts


def test_preview_gif(tmp_path):
    triangles, frames, obstacles = _trajectory(50)
    drawn = write_preview(tmp_path / "fall.gif", triangles=triangles, frames=frames, fps=50.0, obstacles=obstacles,
                          title="falling", size=3.0)
    assert len(drawn) == PREVIEW_FRAMES[".gif"] == 36 and drawn[0] == 0 and drawn[-1] == 49
    assert len(set(drawn.tolist())) == len(drawn)
    images = _gif_frames(tmp_path / "fall.gif")
    assert len(images) == 36 and images[0].shape == (300, 300, 3)
    for image in (images[0], images[-1]):
        assert _cloth_pixels(image) > 500  # the cloth is drawn
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10  # not blank
    assert np.abs(images[0].astype(int) - images[-1].astype(int)).sum() > 0  # it moves


def test_preview_png_contact_sheet(tmp_path):
    triangles, frames, obstacles = _trajectory(20)
    drawn = write_preview(tmp_path / "sheet.png", triangles=triangles, frames=frames, fps=50.0, obstacles=obstacles,
                          max_frames=5, size=2.0)
    assert drawn.tolist() == [0, 5, 10, 14, 19]
    with Image.open(tmp_path / "sheet.png") as im:
        sheet = np.asarray(im.convert("RGB"))
    assert sheet.shape == (2 * 200, 3 * 200, 3)  # 5 panels: 3 columns, 2 rows of 2 x 2 inches at 100 dpi
    assert _cloth_pixels(sheet[:200, :200]) > 100 and _cloth_pixels(sheet[200:, :200]) > 100  # panels 1 and 4


def test_preview_fewer_frames_than_asked(tmp_path):
    triangles, frames, _ = _trajectory(3)
    drawn = write_preview(tmp_path / "short.gif", triangles=triangles, frames=frames, fps=10.0, size=2.0)
    assert drawn.tolist() == [0, 1, 2] and len(_gif_frames(tmp_path / "short.gif")) == 3


@pytest.mark.parametrize("kwargs, match", [
    (dict(path="a.avi"), r"write_preview: path '.*a.avi': expected a file ending in \.gif or \.mp4 or \.png"),
    (dict(max_frames=0), "max_frames must be an integer >= 1, got 0"),
    (dict(fps=0.0), "fps must be a finite number > 0"),
    (dict(frames=[]), "frames is empty"),
    (dict(triangles=[[0, 1, 99]]), r"triangle 0 \[0, 1, 99\] has an index out of range"),
    (dict(obstacles=[("ball", np.zeros((4, 8, 3)), [[0, 1, 2]])]), "obstacle 'ball' has 4 frames of vertices"),
])
def test_preview_bad_input_names_it(tmp_path, kwargs, match):
    triangles, frames, _ = _trajectory(5)
    args = dict(path="p.gif", triangles=triangles, frames=frames, fps=10.0, obstacles=())
    args.update(kwargs)
    args["path"] = tmp_path / args["path"]
    with pytest.raises(ValueError, match=match):
        write_preview(**args)
    assert not (tmp_path / "p.gif").exists()


def test_preview_mp4_needs_ffmpeg(tmp_path, monkeypatch):
    import matplotlib

    monkeypatch.setitem(matplotlib.rcParams, "animation.ffmpeg_path", str(tmp_path / "no-ffmpeg-here"))
    triangles, frames, _ = _trajectory(5)
    with pytest.raises(ValueError, match="MP4 needs ffmpeg on PATH"):
        write_preview(tmp_path / "v.mp4", triangles=triangles, frames=frames, fps=10.0)


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not on PATH")
def test_preview_mp4(tmp_path):
    triangles, frames, obstacles = _trajectory(10)
    drawn = write_preview(tmp_path / "v.mp4", triangles=triangles, frames=frames, fps=10.0, obstacles=obstacles)
    assert len(drawn) == 10 and (tmp_path / "v.mp4").stat().st_size > 1000


SCENE = """\
name = "preview-test"
[sim]
dt = 0.02
steps = 12
[cloth]
grid = { res = [4, 4], size = [0.5, 0.5] }
material = "gray-interlock"
[[obstacles]]
name = "ball"
shape = "sphere"
radius = 0.1
pos = [0.25, 0.25, -0.3]
"""


def test_simulate_preview(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    status = main(["simulate", str(scene), "--device", "cpu", "--usd", str(tmp_path / "out.usda"),
                   "--preview", str(tmp_path / "out.gif")])
    assert status == 0, capsys.readouterr().err
    assert f"wrote {tmp_path / 'out.gif'} (13 frames drawn)" in capsys.readouterr().out
    images = _gif_frames(tmp_path / "out.gif")
    assert len(images) == 13 and _cloth_pixels(images[-1]) > 500


def test_simulate_preview_bad_suffix_fails_before_simulating(tmp_path, capsys):
    status = main(["simulate", "free-fall", "--device", "cpu", "--usd", str(tmp_path / "out.usda"),
                   "--preview", str(tmp_path / "out.avi")])
    assert status == 2
    err = capsys.readouterr().err
    assert "--preview" in err and "out.avi" in err and ".gif or .mp4 or .png" in err
    assert not (tmp_path / "out.usda").exists()


def test_estimate_preview(tmp_path, capsys):
    path = tmp_path / "fit.gif"
    assert main(["estimate", "--material", "tango-red-jet-set", "--iters", "1", "--steps", "4", "--device", "cpu",
                 "--preview", str(path)]) == 0
    assert f"wrote {path}" in capsys.readouterr().out
    images = _gif_frames(path)
    assert len(images) == 3 and _cloth_pixels(images[-1]) > 500  # the frames the fit compares: 0, 2 and 4 steps


def test_preview_of_many_jobs_is_a_usage_error(tmp_path, capsys):
    assert main(["control", "--starts", "2", "--preview", str(tmp_path / "c.gif")]) == 2
    assert "--preview writes one run's trajectory; this command runs 2 jobs" in capsys.readouterr().err
    assert main(["estimate", "--preview", str(tmp_path / "e.jpg")]) == 2
    assert "--preview" in capsys.readouterr().err
