"""The public surface: every Model, State and Control field is documented with its shape and unit, and importing
warpcloth pulls in none of the optional heavy packages."""

import ast
import inspect
import re
import subprocess
import sys

import pytest

import warpcloth as wc
from warpcloth import model as model_module

UNIT = re.compile(r"\[[^\]]+\]")
"""A unit in brackets: [m], [m/s], [kg/m^2], ...; [-] for what has none (counts, indices, flags, names)."""
SHAPE = re.compile(r"\((?:[\w +\-*.]+,)+[\w +\-*.]*\)|\bscalar\b")
"""A shape such as (particle_count,) or (tri_count, 3), or the word scalar."""


def field_docstrings(cls) -> dict[str, str | None]:
    """Each field of ``cls`` with the string literal that follows its definition (None if there is none): class-level
    annotated fields, and ``self.name = ...`` assignments in ``__init__``."""
    tree = ast.parse(inspect.getsource(cls))
    body = tree.body[0].body
    init = next((node for node in body if isinstance(node, ast.FunctionDef) and node.name == "__init__"), None)
    docs = {}
    for statements in (body, [] if init is None else init.body):
        for node, following in zip(statements, statements[1:] + [None]):
            name = None
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                name = node.target.id
            elif (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Attribute)
                  and isinstance(node.targets[0].value, ast.Name) and node.targets[0].value.id == "self"):
                name = node.targets[0].attr
            if name is None or name.startswith("_"):
                continue
            doc = None
            if (isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                    and isinstance(following.value.value, str)):
                doc = following.value.value
            docs[name] = doc
    return docs


@pytest.mark.parametrize("cls", [model_module.Model, model_module.State, model_module.Control])
def test_every_field_has_a_docstring_with_shape_and_unit(cls):
    docs = field_docstrings(cls)
    assert len(docs) >= 3
    missing = [name for name, doc in docs.items() if not doc]
    assert not missing, f"{cls.__name__} fields without a docstring: {missing}"
    no_shape = [name for name, doc in docs.items() if not SHAPE.search(doc)]
    assert not no_shape, f"{cls.__name__} field docstrings without a shape: {no_shape}"
    no_unit = [name for name, doc in docs.items() if not UNIT.search(doc)]
    assert not no_unit, f"{cls.__name__} field docstrings without a unit in brackets: {no_unit}"


def test_field_docstring_reader_sees_every_dataclass_field():
    # the reader must not miss fields, or the test above could pass on an undocumented one
    import dataclasses

    assert set(field_docstrings(model_module.Model)) == {f.name for f in dataclasses.fields(model_module.Model)}
    assert {"particle_x", "particle_v", "time", "step", "particle_dv"} <= set(field_docstrings(model_module.State))


def test_import_pulls_in_no_optional_package():
    code = ("import sys, warpcloth; heavy = [m for m in ('torch', 'pxr', 'matplotlib') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"import warpcloth imported {out}"
    # and it leaves no generic top-level 'kernels' module behind (DESIGN.md: kernels/ installs as warpcloth.kernels)
    code = "import sys, warpcloth; print('kernels' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() \
        == "False"


def test_all_names_exist():
    for name in wc.__all__:
        assert hasattr(wc, name), name
