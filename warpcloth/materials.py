"""Cloth materials in ARCSim's raw units: the data-driven anisotropic model and ten measured fabrics of H. Wang,
R. Ramamoorthi and J. F. O'Brien, "Data-Driven Elastic Models for Cloth" (SIGGRAPH 2011). Negative coupling and shear
entries act as zero stiffness (SPEC.md sections 1.2 and 1.3)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources

import numpy as np

__all__ = [
    "DIFFCLOTH_BENDING_SCALE",
    "DIFFCLOTH_STRETCHING_SCALE",
    "PRESET_NAMES",
    "SEED_INITIAL_GUESS_NAMES",
    "Material",
    "load_material_json",
    "mean_material",
    "preset",
]

STRETCHING_SHAPE = (6, 4)
BENDING_SHAPE = (3, 5)

DIFFCLOTH_STRETCHING_SCALE = 1e3
"""Multiply a stretching table in the seed code's (DiffCloth's) scaled units by this to get raw units [N/m]."""
DIFFCLOTH_BENDING_SCALE = 1e-4
"""Multiply a bending table in the seed code's scaled units by this to get raw units [N*m]."""

_STRETCHING_COLUMNS = ("warp stretch k0", "coupling k1", "weft stretch k2", "shear k3")
# Columns that must be >= 0. Coupling and shear may be negative in measured data; the model applies relu.
_NONNEGATIVE_STRETCHING_COLUMNS = (0, 2)


def check_material_values(where: str, *, density=None, stretching=None, bending=None) -> None:
    """Raise ValueError naming ``where`` and the entry for a non-finite value, a density <= 0, or a negative warp/weft
    stretch (columns 0 and 2) or bending entry. Shapes: density (...,), stretching (..., 6, 4), bending (..., 3, 5)."""

    def entry(name, index):
        return f"{name}[{', '.join(str(int(i)) for i in index)}]" if len(index) else name

    tables = {"density": density, "stretching": stretching, "bending": bending}
    tables = {k: np.asarray(v, dtype=np.float64) for k, v in tables.items() if v is not None}
    for name, table in tables.items():
        bad = np.argwhere(~np.isfinite(table))
        if len(bad):
            raise ValueError(f"{where}: {entry(name, bad[0])} is not finite ({table[tuple(bad[0])]})")
    if "density" in tables:
        bad = np.argwhere(tables["density"] <= 0.0)
        if len(bad):
            value = tables["density"][tuple(bad[0])]
            raise ValueError(f"{where}: {entry('density', bad[0])} must be > 0, got {value}")
    if "stretching" in tables:
        stretch = tables["stretching"][..., list(_NONNEGATIVE_STRETCHING_COLUMNS)]
        bad = np.argwhere(stretch < 0.0)
        if len(bad):
            index = (*bad[0][:-1], _NONNEGATIVE_STRETCHING_COLUMNS[bad[0][-1]])
            raise ValueError(f"{where}: {entry('stretching', index)} ({_STRETCHING_COLUMNS[index[-1]]}) must be "
                             f">= 0, got {tables['stretching'][tuple(index)]}")
    if "bending" in tables:
        bad = np.argwhere(tables["bending"] < 0.0)
        if len(bad):
            value = tables["bending"][tuple(bad[0])]
            raise ValueError(f"{where}: {entry('bending', bad[0])} must be >= 0, got {value}")


@dataclass(eq=False)
class Material:
    """A fabric's elastic tables in raw units, copied to float64 and validated on construction; equality is identity.

    Attributes:
        density: Area density [kg/m^2], before ``thicken``.
        stretching: Stretching table [N/m], shape (6, 4), before ``thicken``. Row 0: small strain (k0 warp,
            k1 coupling, k2 weft, k3 shear); rows 1-5: the same at strain 1/6 along 0, 22.5, 45, 67.5, 90 degrees.
        bending: Bending table [N*m], shape (3, 5), before ``thicken``: directions 0, 45, 90 degrees by curvature
            samples every 5 m^-1.
        thicken: Multiplies density, stretching and bending (ARCSim's ``thicken``).
        name: A label for messages and output.
    """

    density: float
    stretching: np.ndarray
    bending: np.ndarray
    thicken: float = 1.0
    name: str = "custom"

    def __post_init__(self) -> None:
        self.stretching = _as_float_table(self.stretching, "stretching", STRETCHING_SHAPE, self.name)
        self.bending = _as_float_table(self.bending, "bending", BENDING_SHAPE, self.name)
        self.density = _as_float_scalar(self.density, "density", self.name)
        self.thicken = _as_float_scalar(self.thicken, "thicken", self.name)
        self.validate()

    def validate(self) -> None:
        """Check the tables as :func:`check_material_values` does, and their shapes and ``thicken`` > 0."""
        where = f"material '{self.name}'"
        for fname in ("density", "thicken"):
            value = _as_float_scalar(getattr(self, fname), fname, self.name)
            if not math.isfinite(value):
                raise ValueError(f"{where}: {fname} is not finite ({value})")
            if value <= 0.0:
                raise ValueError(f"{where}: {fname} must be > 0, got {value}")
        # Re-read the fields: they are public and may have been reassigned since construction.
        stretching = _as_float_table(self.stretching, "stretching", STRETCHING_SHAPE, self.name)
        bending = _as_float_table(self.bending, "bending", BENDING_SHAPE, self.name)
        check_material_values(where, stretching=stretching, bending=bending)

    @classmethod
    def isotropic(
        cls,
        *,
        density: float,
        stretch_stiffness: float,
        shear_stiffness: float,
        poisson_coupling: float = 0.0,
        bend_stiffness: float,
        thicken: float = 1.0,
        name: str = "isotropic",
    ) -> Material:
        """The same stiffness at every strain and in every direction: ``density`` [kg/m^2], warp and weft
        ``stretch_stiffness`` k0 = k2, ``shear_stiffness`` k3, ``poisson_coupling`` k1 [N/m], ``bend_stiffness`` [N*m];
        energy per rest area ``psi = 1/2 (k0 G00^2 + 2 k1 G00 G11 + k2 G11^2) + k3 G01^2`` (G: Green strain) times
        ``thicken``, the table holding half of each stiffness. ValueError naming a negative or non-finite stiffness."""
        params = {
            "stretch_stiffness": stretch_stiffness,
            "shear_stiffness": shear_stiffness,
            "poisson_coupling": poisson_coupling,
            "bend_stiffness": bend_stiffness,
        }
        for pname, value in params.items():
            value = _as_float_scalar(value, pname, name)
            if not math.isfinite(value) or value < 0.0:
                raise ValueError(f"Material.isotropic: {pname} must be finite and >= 0, got {value}")
            params[pname] = value
        s, g, c = params["stretch_stiffness"], params["shear_stiffness"], params["poisson_coupling"]
        row = np.array([s, c, s, g], dtype=np.float64) / 2.0
        return cls(
            density=density,
            stretching=np.tile(row, (STRETCHING_SHAPE[0], 1)),
            bending=np.full(BENDING_SHAPE, params["bend_stiffness"], dtype=np.float64),
            thicken=thicken,
            name=name,
        )

    def copy(self) -> Material:
        """Returns a deep copy."""
        return Material(
            density=self.density,
            stretching=self.stretching.copy(),
            bending=self.bending.copy(),
            thicken=self.thicken,
            name=self.name,
        )

    def scaled(self, *, density: float = 1.0, stretching: float = 1.0, bending: float = 1.0) -> Material:
        """A new material with density (> 0), stretching and bending (>= 0) multiplied by these factors; ValueError
        naming a factor not finite or out of range."""
        _check_multiplier(density, "density", positive=True)
        _check_multiplier(stretching, "stretching")
        _check_multiplier(bending, "bending")
        return Material(
            density=self.density * density,
            stretching=self.stretching * stretching,
            bending=self.bending * bending,
            thicken=self.thicken,
            name=self.name,
        )


def _as_float_scalar(value, fname: str, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"material '{name}': {fname} must be a number, got {type(value).__name__}")
    return float(value)


def _as_float_table(value, fname: str, shape: tuple[int, int], name: str) -> np.ndarray:
    try:
        table = np.array(value, dtype=np.float64)  # copy: a material never aliases the caller's array
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"material '{name}': {fname} must be a {shape[0]}x{shape[1]} table of numbers ({exc})"
        ) from None
    if table.shape != shape:
        raise ValueError(f"material '{name}': {fname} must have shape {shape}, got {table.shape}")
    return table


def _check_multiplier(value: float, pname: str, *, positive: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{pname} must be a number, got {type(value).__name__}")
    if not math.isfinite(value) or value < 0.0 or (positive and value == 0.0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{pname} must be finite and {bound}, got {value}")


# name: {"density" [kg/m^2], "stretching" 6x4 [N/m], "bending" 3x5 [N*m]}, raw values at full precision
_PRESETS: dict[str, dict] = json.loads(resources.files("warpcloth.data").joinpath("materials.json").read_text("utf-8"))

PRESET_NAMES: tuple[str, ...] = tuple(_PRESETS)
"""The ten measured fabrics, named as ARCSim's material files."""

SEED_INITIAL_GUESS_NAMES: tuple[str, ...] = tuple(
    n for n in PRESET_NAMES if n not in ("royal-target", "white-dots-on-blk")
)
"""The 8 fabrics whose mean is the seed's start point ``init_mat.json`` (all but royal-target, white-dots-on-blk)."""


def preset(name: str, *, thicken: float = 1.0) -> Material:
    """One of the measured fabrics, ``name`` from :data:`PRESET_NAMES`, with ``thicken``; ValueError listing the
    valid names for an unknown one."""
    if name not in _PRESETS:
        raise ValueError(f"unknown material preset {name!r}; valid names: {', '.join(PRESET_NAMES)}")
    data = _PRESETS[name]
    return Material(density=data["density"], stretching=data["stretching"], bending=data["bending"],
                    thicken=thicken, name=name)


def mean_material(names: Sequence[str], *, thicken: float = 1.0) -> Material:
    """Element-wise mean of the presets ``names``, in raw units, with ``thicken``; ValueError when ``names`` is empty
    or a string, or lists an unknown preset."""
    if isinstance(names, str):
        raise ValueError(f"mean_material: names must be a sequence of preset names, not the string {names!r}")
    if len(names) == 0:
        raise ValueError("mean_material: names is empty")
    mats = [preset(n) for n in names]
    return Material(
        density=float(np.mean([m.density for m in mats])),
        stretching=np.mean([m.stretching for m in mats], axis=0),
        bending=np.mean([m.bending for m in mats], axis=0),
        thicken=thicken,
        name="mean(" + ",".join(names) + ")",
    )


def load_material_json(
    path: str | os.PathLike,
    *,
    stretching_mult: float = 1.0,
    bending_mult: float = 1.0,
    thicken: float = 1.0,
) -> Material:
    """Load an ARCSim material file ``{"density": ..., "stretching": 6x4, "bending": 3x5}``, each table times its
    ``*_mult`` (seed files: the ``DIFFCLOTH_*_SCALE`` constants), with ``thicken``; ValueError naming the file and
    key for a missing or unknown key (``damping``) or an invalid value."""
    _check_multiplier(stretching_mult, "stretching_mult")
    _check_multiplier(bending_mult, "bending_mult")
    with open(path, encoding="utf-8") as f:
        try:
            data = json.load(f)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object with keys density, stretching, bending")
    required = ("density", "stretching", "bending")
    for key in required:
        if key not in data:
            raise ValueError(f"{path}: missing key {key!r}")
    unknown = sorted(set(data) - set(required))
    if unknown:
        raise ValueError(
            f"{path}: unsupported key(s) {', '.join(map(repr, unknown))}; supported: {', '.join(required)}"
        )
    name = os.path.splitext(os.path.basename(os.fspath(path)))[0]
    try:
        stretching = _as_float_table(data["stretching"], "stretching", STRETCHING_SHAPE, name)
        bending = _as_float_table(data["bending"], "bending", BENDING_SHAPE, name)
        return Material(
            density=data["density"],
            stretching=stretching * stretching_mult,
            bending=bending * bending_mult,
            thicken=thicken,
            name=name,
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
