"""Cloth materials: the data-driven anisotropic model of Wang et al. 2011, as ARCSim stores it.

A :class:`Material` holds the raw measured tables of one fabric:

- ``density``: area density [kg/m^2].
- ``stretching``: a (6, 4) table [N/m]. Row 0 holds the four small-strain coefficients
  (k0 warp stretch, k1 warp-weft coupling, k2 weft stretch, k3 shear), valid for every direction; rows 1-5 hold the
  same four coefficients at a principal stretch of 7/6 (strain 1/6) along 0, 22.5, 45, 67.5 and 90 degrees.
- ``bending``: a (3, 5) table [N*m]. Rows are the bending directions 0, 45 and 90 degrees; columns are five
  curvature samples, one every 5 m^-1.
- ``thicken``: ARCSim's ``thicken`` factor, which multiplies density, stretching and bending (every demo of the seed
  method uses 2).

The physics core interpolates the stretching table and uses ``k = 2 * relu(value) * thicken`` (SPEC.md section 1.2),
and ``ke = relu(bilinear(bending)) * thicken`` for bending (section 1.3). Because of the relu, negative coupling and
shear entries (the measured data has several) act as zero stiffness where the interpolated value is negative; negative
warp/weft stretch or bending entries are rejected by :meth:`Material.validate`.

Units are the *raw* units of the measurements, i.e. ARCSim's. The seed method's code (DiffCloth) stores stretching
divided by 1e3 and bending multiplied by 1e4; load such files with
``load_material_json(path, stretching_mult=DIFFCLOTH_STRETCHING_SCALE, bending_mult=DIFFCLOTH_BENDING_SCALE)``.

The ten presets are the fabrics measured by H. Wang, R. Ramamoorthi and J. F. O'Brien, "Data-Driven Elastic Models
for Cloth: Modeling and Measurement", ACM Trans. Graph. 30(4) (SIGGRAPH 2011),
http://graphics.berkeley.edu/papers/Wang-DDE-2011-08/. The numbers are those of the ARCSim material database
(``arcsim/materials/*.json``), shipped at the files' full precision in ``warpcloth/data/materials.json``.
"""

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
"""Shape of the stretching table: (small strain + 5 directions, 4 coefficients)."""
BENDING_SHAPE = (3, 5)
"""Shape of the bending table: (3 directions, 5 curvature samples)."""

DIFFCLOTH_STRETCHING_SCALE = 1e3
"""Multiply a stretching table in the seed code's scaled units by this to get raw units [N/m]."""
DIFFCLOTH_BENDING_SCALE = 1e-4
"""Multiply a bending table in the seed code's scaled units by this to get raw units [N*m]."""

_STRETCHING_COLUMNS = ("warp stretch k0", "coupling k1", "weft stretch k2", "shear k3")
# Columns that must be >= 0. Coupling and shear may be negative in measured data; the model applies relu.
_NONNEGATIVE_STRETCHING_COLUMNS = (0, 2)


def check_material_values(where: str, *, density=None, stretching=None, bending=None) -> None:
    """Raise ValueError naming ``where``, the table and the entry for a value no material may hold: any non-finite
    value, a density <= 0, a negative warp/weft stretch entry (stretching columns 0 and 2) or a negative bending
    entry. Tables may carry leading dimensions (one row per material: the model's arrays, the torch bridge's
    tensors): density (...,), stretching (..., 6, 4), bending (..., 3, 5)."""

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
    """A fabric's measured elastic tables in raw Wang et al. 2011 units.

    Construction converts the tables to float64 arrays (a copy) and calls :meth:`validate`. Equality is identity;
    compare tables with NumPy.

    Attributes:
        density: Area density [kg/m^2], before ``thicken``.
        stretching: Stretching table [N/m], shape (6, 4), before ``thicken``. Row 0 = small-strain
            (k0 warp, k1 coupling, k2 weft, k3 shear); rows 1-5 = the same at strain 1/6 along
            0, 22.5, 45, 67.5, 90 degrees. Columns 1 and 3 may be negative: the model uses
            ``k = 2 * relu(interpolated value) * thicken``.
        bending: Bending table [N*m], shape (3, 5), before ``thicken``. Rows = directions 0, 45, 90 degrees;
            columns = curvature samples every 5 m^-1.
        thicken: Multiplies density, stretching and bending (ARCSim's ``thicken``; the seed demos use 2).
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
        """Checks the tables.

        Raises:
            ValueError: naming the field (and the ``(row, col)`` entry) when a value is NaN or infinite, ``density``
                or ``thicken`` is not positive, a table has the wrong shape, a warp/weft stretch entry
                (stretching columns 0 and 2) is negative, or a bending entry is negative.
        """
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
        """Builds a material whose stiffness is the same at every strain and in every direction.

        With ``k0 = k2 = stretch_stiffness``, ``k1 = poisson_coupling`` and ``k3 = shear_stiffness`` the
        stretching energy per unit rest area is
        ``psi = 1/2 (k0 G00^2 + 2 k1 G00 G11 + k2 G11^2) + k3 G01^2`` (G = Green strain), times ``thicken``.
        Since the model uses ``k = 2 * relu(table value) * thicken``, the table stores half of each stiffness.
        Every bending entry is ``bend_stiffness``.

        Args:
            density: Area density [kg/m^2].
            stretch_stiffness: Warp and weft stretch stiffness k0 = k2 [N/m].
            shear_stiffness: Shear stiffness k3 [N/m].
            poisson_coupling: Warp-weft coupling k1 [N/m].
            bend_stiffness: Bending stiffness [N*m].
            thicken: Multiplies density and both stiffnesses.
            name: Label.

        Raises:
            ValueError: naming the parameter when a stiffness is negative or not finite (a negative coupling would
                be zeroed by the model's relu, so it is rejected rather than silently ignored).
        """
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
        """Returns a new material with each table multiplied by a factor.

        Args:
            density: Factor for the density (> 0).
            stretching: Factor for the stretching table (>= 0).
            bending: Factor for the bending table (>= 0).

        Raises:
            ValueError: naming the factor when it is not finite or out of range.
        """
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


# name: {"density" [kg/m^2], "stretching" 6x4 [N/m], "bending" 3x5 [N*m]}, raw ARCSim / Wang et al. 2011 values,
# shipped as package data in the ARCSim material-file layout.
_PRESETS: dict[str, dict] = json.loads(resources.files("warpcloth.data").joinpath("materials.json").read_text("utf-8"))

PRESET_NAMES: tuple[str, ...] = tuple(_PRESETS)
"""The ten measured fabrics, named as ARCSim's material files."""

SEED_INITIAL_GUESS_NAMES: tuple[str, ...] = tuple(
    n for n in PRESET_NAMES if n not in ("royal-target", "white-dots-on-blk")
)
"""The 8 fabrics whose mean is the seed's optimisation start point ``init_mat.json`` (all but royal-target and
white-dots-on-blk)."""


def preset(name: str, *, thicken: float = 1.0) -> Material:
    """Returns one of the measured fabrics.

    Args:
        name: One of :data:`PRESET_NAMES`.
        thicken: Multiplies density, stretching and bending (the seed demos use 2).

    Raises:
        ValueError: listing the valid names when ``name`` is unknown.
    """
    if name not in _PRESETS:
        raise ValueError(f"unknown material preset {name!r}; valid names: {', '.join(PRESET_NAMES)}")
    data = _PRESETS[name]
    return Material(density=data["density"], stretching=data["stretching"], bending=data["bending"],
                    thicken=thicken, name=name)


def mean_material(names: Sequence[str], *, thicken: float = 1.0) -> Material:
    """Element-wise mean of presets, in raw units.

    ``mean_material(SEED_INITIAL_GUESS_NAMES)`` is the seed's initial guess ``init_mat.json`` converted to raw units.

    Args:
        names: Preset names (at least one).
        thicken: ``thicken`` of the result.

    Raises:
        ValueError: when ``names`` is empty or a string, or lists an unknown preset.
    """
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
    """Loads an ARCSim material file ``{"density": ..., "stretching": 6x4, "bending": 3x5}``.

    The result holds ``file value * mult``. Raw Wang/ARCSim files need no multipliers; the seed code's scaled files
    (e.g. ``init_mat.json``) need ``stretching_mult=DIFFCLOTH_STRETCHING_SCALE, bending_mult=DIFFCLOTH_BENDING_SCALE``.

    Args:
        path: The JSON file.
        stretching_mult: Multiplies the stretching table.
        bending_mult: Multiplies the bending table.
        thicken: ``thicken`` of the result.

    Raises:
        ValueError: naming the file and key when a key is missing or unknown (other ARCSim material keys such as
            ``damping`` are not supported and not ignored), or the values are invalid.
    """
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
