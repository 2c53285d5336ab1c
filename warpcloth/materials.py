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
(``arcsim/materials/*.json``), written here at the files' full precision.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

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
        for fname, table in (("stretching", stretching), ("bending", bending)):
            bad = np.argwhere(~np.isfinite(table))
            if len(bad):
                r, c = (int(i) for i in bad[0])
                raise ValueError(f"{where}: {fname}[{r}, {c}] is not finite ({table[r, c]})")
        for c in _NONNEGATIVE_STRETCHING_COLUMNS:
            for r in range(STRETCHING_SHAPE[0]):
                if stretching[r, c] < 0.0:
                    raise ValueError(
                        f"{where}: stretching[{r}, {c}] ({_STRETCHING_COLUMNS[c]}) must be >= 0, got {stretching[r, c]}"
                    )
        bad = np.argwhere(bending < 0.0)
        if len(bad):
            r, c = (int(i) for i in bad[0])
            raise ValueError(f"{where}: bending[{r}, {c}] must be >= 0, got {bending[r, c]}")

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


# name: (density [kg/m^2], stretching 6x4 [N/m], bending 3x5 [N*m]), raw ARCSim / Wang et al. 2011 values.
_PRESETS: dict[str, tuple[float, tuple[tuple[float, ...], ...], tuple[tuple[float, ...], ...]]] = {
    "11oz-black-denim": (
        0.324,
        (
            (205.352005, 10.234077, 1013.88629, 53.387184),
            (232.027634, 40.646339, 1052.84289, 64.980499),
            (224.592209, 40.384563, 1054.43444, 67.184807),
            (225.951050, 62.095657, 1059.59741, 83.992020),
            (226.039566, 40.502792, 1058.27771, 75.118423),
            (225.767487, 40.917892, 1051.55712, 71.810631),
        ),
        (
            (64.196457e-6, 60.286175e-6, 60.943428e-6, 62.433697e-6, 19.824701e-6),
            (73.384567e-6, 59.671982e-6, 61.080757e-6, 68.242569e-6, 36.033474e-6),
            (96.951576e-6, 107.848228e-6, 113.060738e-6, 120.569740e-6, 79.781021e-6),
        ),
    ),
    "camel-ponte-roma": (
        0.284,
        (
            (31.146198, -12.802702, 44.028667, 31.896357),
            (78.707756, 26.754574, 268.680725, 27.743423),
            (67.368431, 77.767944, 182.273407, -14.661531),
            (113.367035, 54.802021, 175.126572, 44.657330),
            (144.294830, 111.404854, 138.422150, -29.861851),
            (143.933365, 49.654823, 191.777588, 39.491055),
        ),
        (
            (36.348366e-6, 49.585537e-6, 45.744080e-6, 47.413387e-6, 20.726685e-6),
            (33.013252e-6, 29.744385e-6, 35.103642e-6, 34.041019e-6, 14.439938e-6),
            (37.157593e-6, 34.107452e-6, 33.229435e-6, 34.685535e-6, 10.439938e-6),
        ),
    ),
    "gray-interlock": (
        0.187,
        (
            (16.593832, -14.695990, 34.477123, 36.860302),
            (46.364765, 53.694656, 261.013855, -29.691301),
            (49.285110, 87.596100, 206.373993, 22.768457),
            (123.989220, 105.181770, 365.966217, 44.217571),
            (139.686325, 73.592560, 413.553162, -174.43853),
            (127.443810, 85.848587, 405.872833, 32.238411),
        ),
        (
            (23.191698e-6, 32.932217e-6, 34.406498e-6, 39.014420e-6, 23.382786e-6),
            (24.749964e-6, 18.651314e-6, 16.370552e-6, 25.095791e-6, 8.860165e-6),
            (14.267624e-6, 7.052906e-6, 14.515154e-6, 24.665127e-6, 19.383726e-6),
        ),
    ),
    "ivory-rib-knit": (
        0.276,
        (
            (42.871021, -0.234556, 65.166023, 83.175644),
            (52.422512, 7.219094, 245.337158, -31.129513),
            (29.482058, -5.146112, 127.130753, 13.068157),
            (91.209549, 4.940307, 109.746452, 27.609430),
            (48.973385, -0.967226, 147.696823, -49.282963),
            (105.649139, 0.416488, 254.593491, 3.472504),
        ),
        (
            (46.237591e-6, 63.086697e-6, 83.192772e-6, 97.574425e-6, 80.726685e-6),
            (30.015930e-6, 30.097424e-6, 30.172081e-6, 30.648300e-6, 24.726685e-6),
            (32.243889e-6, 37.341282e-6, 38.817448e-6, 39.812527e-6, 30.437820e-6),
        ),
    ),
    "navy-sparkle-sweat": (
        0.224,
        (
            (12.486332, -19.875324, 3.272434, 17.616289),
            (32.172089, 56.012760, 283.466370, -2.438436),
            (48.565407, 94.126335, 180.101227, 4.439080),
            (77.093796, 2.958664, 91.251160, 6.107700),
            (126.205986, 84.471718, 305.131531, 38.495132),
            (92.343170, 117.527084, 243.264908, 47.338436),
        ),
        (
            (59.469658e-6, 37.500004e-6, 35.787308e-6, 35.737106e-6, 21.033506e-6),
            (40.072277e-6, 37.446949e-6, 35.206612e-6, 24.871773e-6, 9.033506e-6),
            (45.625023e-6, 39.520981e-6, 30.734119e-6, 23.301662e-6, 13.033506e-6),
        ),
    ),
    "pink-ribbon-brown": (
        0.228,
        (
            (151.503906, 106.028160, 244.830673, 30.250183),
            (164.124344, 33.689709, 268.195221, 30.074625),
            (152.584641, 107.251373, 210.614838, -62.760571),
            (209.604172, 175.223465, 220.198120, 129.643188),
            (98.879021, 107.085518, 326.209442, 44.475986),
            (96.805817, 54.626881, 359.792633, 30.340616),
        ),
        (
            (117.070122e-6, 202.682922e-6, 298.615936e-6, 244.588867e-6, 238.437820e-6),
            (87.509773e-6, 36.396919e-6, 103.628098e-6, 91.630119e-6, 97.175949e-6),
            (59.774277e-6, 59.260632e-6, 64.199661e-6, 55.017326e-6, 59.221714e-6),
        ),
    ),
    "royal-target": (
        0.220,
        (
            (2016.55456, 9.170511, 2034.97644, 104.759674),
            (2109.51684, 38.604588, 2173.93969, 19.129177),
            (2109.78002, 60.165310, 2155.51367, 27.817890),
            (2110.33349, 30.987429, 2135.07910, 121.482445),
            (2109.16015, 72.393326, 2124.13525, 40.810982),
            (2109.52612, 63.424015, 2152.73852, 39.885654),
        ),
        (
            (125.409805e-6, 167.284561e-6, 215.412750e-6, 215.090790e-6, 223.861038e-6),
            (107.997696e-6, 120.583267e-6, 144.141678e-6, 140.606689e-6, 153.048309e-6),
            (125.409805e-6, 167.284561e-6, 215.412750e-6, 215.090790e-6, 227.861038e-6),
        ),
    ),
    "tango-red-jet-set": (
        0.113,
        (
            (43.067627, 54.373299, 171.424835, 14.314700),
            (75.151695, 82.195221, 236.163773, -7.230383),
            (57.548206, 89.637825, 224.553848, 3.932043),
            (107.244377, 124.801788, 364.583557, 41.386868),
            (178.734039, 178.488907, 371.764618, -30.898058),
            (227.028687, -21.865427, 404.867188, 62.636021),
        ),
        (
            (14.293814e-6, 8.949391e-6, 30.011126e-6, 36.081490e-6, 18.363136e-6),
            (21.951700e-6, 22.446325e-6, 18.408735e-6, 19.598495e-6, 12.071854e-6),
            (20.345654e-6, 22.696880e-6, 15.698071e-6, 13.466827e-6, 7.556618e-6),
        ),
    ),
    "white-dots-on-blk": (
        0.128,
        (
            (2002.08618, 0.345588, 2027.48559, 19.189022),
            (2107.22753, 36.371597, 2171.73339, 16.904713),
            (2107.29882, 57.936157, 2153.30712, 24.392872),
            (2107.73291, 28.389059, 2132.72607, 101.462021),
            (2106.93750, 70.149529, 2121.87353, 38.054455),
            (2107.30786, 61.216290, 2150.47680, 37.668823),
        ),
        (
            (51.713814e-6, 36.506981e-6, 66.360748e-6, 52.729267e-6, 15.221714e-6),
            (40.659470e-6, 10.401686e-6, 20.847820e-6, 30.993469e-6, 12.726685e-6),
            (31.282822e-6, 22.910311e-6, 26.350384e-6, 30.637762e-6, 16.726685e-6),
        ),
    ),
    "white-swim-solid": (
        0.204,
        (
            (47.971176, 6.834521, 104.615456, 60.773663),
            (40.369045, 23.092957, 169.666290, -24.681890),
            (40.291599, 48.142597, 138.261612, 9.002558),
            (51.393467, -32.966949, 79.881721, 35.973194),
            (51.500938, 1.868910, 63.693932, -37.540417),
            (68.621185, 40.131950, 124.468513, 36.199604),
        ),
        (
            (60.237942e-6, 56.357208e-6, 69.698593e-6, 55.305969e-6, 34.705532e-6),
            (58.803211e-6, 63.121964e-6, 61.379181e-6, 47.971302e-6, 19.383726e-6),
            (51.018833e-6, 50.741455e-6, 50.570576e-6, 50.006001e-6, 24.556618e-6),
        ),
    ),
}

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
    density, stretching, bending = _PRESETS[name]
    return Material(density=density, stretching=stretching, bending=bending, thicken=thicken, name=name)


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
