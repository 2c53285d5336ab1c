"""Checks of single TOML values for the scene parser and the task specs: each takes the key path of the value it
checks (``"cloth.grid.res[0]"``) and raises :class:`_SceneError`, a ``ValueError`` naming that path."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from warpcloth import materials as _materials


class _SceneError(ValueError):
    pass


def _err(path: str, message: str) -> _SceneError:
    return _SceneError(f"{path}: {message}" if path else message)


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array", dict: "table"}.get(
        type(value), type(value).__name__
    )


def _table(value: Any, path: str) -> dict:
    if not isinstance(value, dict):
        raise _err(path, f"expected a table, got {_type_name(value)}")
    return value


def _check_keys(table: dict, path: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> None:
    for key in table:
        if key not in allowed:
            full = f"{path}.{key}" if path else key
            raise _err(full, f"unknown key; allowed here: {', '.join(allowed)}")
    for key in required:
        if key not in table:
            full = f"{path}.{key}" if path else key
            raise _err(full, "missing required key")


def _float(value: Any, path: str, *, min_value: float | None = None, strict: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _err(path, f"expected a number, got {_type_name(value)}")
    x = float(value)
    if not math.isfinite(x):
        raise _err(path, f"must be finite, got {x}")
    if min_value is not None and (x < min_value or (strict and x == min_value)):
        raise _err(path, f"must be {'>' if strict else '>='} {min_value}, got {x}")
    return x


def _int(value: Any, path: str, *, min_value: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _err(path, f"expected an integer, got {_type_name(value)}")
    if min_value is not None and value < min_value:
        raise _err(path, f"must be >= {min_value}, got {value}")
    return value


def _str(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise _err(path, f"expected a string, got {_type_name(value)}")
    return value


def _vector(value: Any, path: str, n: int = 3) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        got = f"an array of {len(value)}" if isinstance(value, list) else _type_name(value)
        raise _err(path, f"expected an array of {n} numbers, got {got}")
    return tuple(_float(v, f"{path}[{i}]") for i, v in enumerate(value))



def _existing_file(base_dir: Path, value: Any, key: str, context: str) -> Path:
    """``base_dir / value`` (a string at ``key``), which must be a file: a ValueError under ``context`` otherwise."""
    file = base_dir / _str(value, key)
    if not file.is_file():
        raise _err(context, f"file not found: {file}")
    return file


class _Context:
    """Re-raises a ValueError from library code (materials, mesh loading, builder) under a key path."""

    def __init__(self, path: str):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None and issubclass(exc_type, ValueError) and not isinstance(exc, _SceneError):
            raise _err(self.path, str(exc)) from None
        return False



def _choice(value: Any, path: str, choices: tuple[str, ...]) -> str:
    value = _str(value, path)
    if value not in choices:
        raise _err(path, f"unknown value {value!r}; one of: {', '.join(choices)}")
    return value



_MATERIAL_FORMS = (
    "a preset name",
    "{ mean = [names] }",
    "{ file = ..., stretching_mult, bending_mult }",
    "{ density, stretching, bending }",
    "{ density, stretch_stiffness, shear_stiffness, poisson_coupling, bend_stiffness }",
)


def _parse_material(value: Any, path: str, thicken: float, base_dir: Path) -> _materials.Material:
    if isinstance(value, str):
        with _Context(path):
            return _materials.preset(value, thicken=thicken)
    table = _table(value, path) if isinstance(value, dict) else None
    if table is None:
        raise _err(path, f"expected a string or a table, got {_type_name(value)}")
    if "file" in table:
        _check_keys(table, path, ("file", "stretching_mult", "bending_mult"))
        file = _existing_file(base_dir, table["file"], f"{path}.file", path)
        smult = _float(table.get("stretching_mult", 1.0), f"{path}.stretching_mult", min_value=0.0)
        bmult = _float(table.get("bending_mult", 1.0), f"{path}.bending_mult", min_value=0.0)
        with _Context(path):
            return _materials.load_material_json(file, stretching_mult=smult, bending_mult=bmult, thicken=thicken)
    if "mean" in table:
        _check_keys(table, path, ("mean",))
        names = table["mean"]
        if not isinstance(names, list) or not names:
            raise _err(f"{path}.mean", "expected a non-empty array of preset names")
        names = [_str(n, f"{path}.mean[{i}]") for i, n in enumerate(names)]
        with _Context(f"{path}.mean"):
            return _materials.mean_material(names, thicken=thicken)
    if "stretching" in table or "bending" in table:
        required = ("density", "stretching", "bending")
        _check_keys(table, path, required + ("name",), required=required)
        density = _float(table["density"], f"{path}.density")
        tables = {}
        for key, shape in (("stretching", _materials.STRETCHING_SHAPE), ("bending", _materials.BENDING_SHAPE)):
            rows = table[key]
            if not isinstance(rows, list) or len(rows) != shape[0]:
                raise _err(f"{path}.{key}", f"expected {shape[0]} rows of {shape[1]} numbers")
            tables[key] = [_vector(r, f"{path}.{key}[{i}]", shape[1]) for i, r in enumerate(rows)]
        name = _str(table.get("name", "custom"), f"{path}.name")
        with _Context(path):
            return _materials.Material(density=density, thicken=thicken, name=name, **tables)
    if "stretch_stiffness" in table:
        keys = ("density", "stretch_stiffness", "shear_stiffness", "poisson_coupling", "bend_stiffness", "name")
        _check_keys(table, path, keys, required=("density", "stretch_stiffness", "shear_stiffness", "bend_stiffness"))
        kwargs = {k: _float(table[k], f"{path}.{k}") for k in keys[:-1] if k in table}
        name = _str(table.get("name", "isotropic"), f"{path}.name")
        with _Context(path):
            return _materials.Material.isotropic(thicken=thicken, name=name, **kwargs)
    raise _err(path, "unrecognised material table; use one of: " + "; ".join(_MATERIAL_FORMS))



def _grid_index(value: int, extent: int, path: str) -> int:
    """Python-style index into 0..extent-1."""
    if not -extent <= value < extent:
        raise _err(path, f"index {value} out of range for {extent} vertices")
    return value % extent


def _grid_vertex(value: Any, path: str, grid_res: tuple[int, int]) -> int:
    """The particle of grid vertex ``[i, j]`` (Python-style indices)."""
    if not isinstance(value, list) or len(value) != 2:
        raise _err(path, f"expected an array of 2 integers [i, j], got {_type_name(value)}")
    nx, ny = grid_res[0] + 1, grid_res[1] + 1
    i = _grid_index(_int(value[0], f"{path}[0]"), nx, f"{path}[0]")
    j = _grid_index(_int(value[1], f"{path}[1]"), ny, f"{path}[1]")
    return j * nx + i


def _particle_indices(values: Any, path: str, count: int, grid_res, *, grid: bool) -> list[int]:
    """A non-empty array at ``path`` of particle indices (or, ``grid``, grid vertices ``[i, j]``) as indices into a
    cloth of ``count`` particles (``grid_res``: its grid cells, None for a mesh)."""
    if not isinstance(values, list) or not values:
        raise _err(path, f"expected a non-empty array, got {_type_name(values)}")
    if grid and grid_res is None:
        raise _err(path, "needs a grid cloth (cloth.grid)")
    out = []
    for k, value in enumerate(values):
        item = f"{path}[{k}]"
        if grid:
            out.append(_grid_vertex(value, item, grid_res))
            continue
        p = _int(value, item, min_value=0)
        if p >= count:
            raise _err(item, f"particle {p} out of range: the cloth has {count} particles")
        out.append(p)
    return out
