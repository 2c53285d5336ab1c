"""Property-based tests of the loaders (issue 15): random and malformed scene TOML, OBJ text and material JSON
either load or raise ValueError naming the problem; never another exception, never a hang."""

import importlib.resources
import json
import math
import os
import tempfile
import tomllib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from warpcloth.materials import load_material_json
from warpcloth.mesh_io import load_obj
from warpcloth.scene import SCENE_NAMES, scene_from_toml

# FUZZ_EXAMPLES=3000 for a longer search (about 35 s)
SETTINGS = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", 150)), deadline=5000,
                    suppress_health_check=[HealthCheck.too_slow])

# values of every TOML type, odd ones included: NaN, infinities, huge and negative numbers, empty containers
scalars = st.one_of(
    st.integers(-3, 40), st.integers(-10**15, 10**15), st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(), st.text(max_size=12), st.sampled_from(["gray-interlock", "accurate", "../x", "", "particle"]),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=12)


def toml_value(v) -> str:
    """TOML text of a value (inline tables and arrays)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"


def paths(table, prefix=()):
    """Every key path of a parsed TOML document (into tables and arrays of tables)."""
    for key, value in table.items():
        yield (*prefix, key)
        if isinstance(value, dict):
            yield from paths(value, (*prefix, key))
        elif isinstance(value, list) and value and all(isinstance(x, dict) for x in value):
            for i, x in enumerate(value):
                yield from paths(x, (*prefix, key, i))


def dump(table) -> str:
    """A document whose top-level keys are all written inline (TOML allows any table inline)."""
    return "\n".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in table.items()) + "\n"




def embedded_documents():
    return {name: tomllib.loads(importlib.resources.files("warpcloth.scenes").joinpath(f"{name}.toml").read_text())
            for name in SCENE_NAMES}


DOCUMENTS = embedded_documents()
SCENES_DIR = str(importlib.resources.files("warpcloth.scenes"))  # the embedded scenes' meshes are relative to it


def loads_or_value_error(load):
    try:
        load()
    except ValueError as exc:
        assert str(exc), "a ValueError with no message"


@SETTINGS
@given(text=st.text(max_size=200))
def test_random_text_as_a_scene(text):
    loads_or_value_error(lambda: scene_from_toml(text))


@SETTINGS
@given(name=st.sampled_from(sorted(DOCUMENTS)), data=st.data())
def test_embedded_scenes_with_one_value_replaced_or_removed(name, data):
    import copy

    document = copy.deepcopy(DOCUMENTS[name])
    path = data.draw(st.sampled_from(list(paths(document))))
    parent = document
    for key in path[:-1]:
        parent = parent[key]
    if data.draw(st.booleans()):
        parent[path[-1]] = data.draw(values)
    else:
        del parent[path[-1]]
    text = dump(document)
    loads_or_value_error(lambda: scene_from_toml(text, base_dir=SCENES_DIR))


obj_lines = st.one_of(
    st.builds(lambda xs: "v " + " ".join(xs), st.lists(st.sampled_from(["0", "1", "-1", "0.5", "nan", "inf", "1e30",
                                                                        "x", ""]), max_size=4)),
    st.builds(lambda xs: "vt " + " ".join(xs), st.lists(st.sampled_from(["0", "1", "0.5", "nan", "y"]), max_size=3)),
    st.builds(lambda xs: "f " + " ".join(xs), st.lists(st.sampled_from(["1", "2", "3", "4", "-1", "0", "9",
                                                                        "1/1", "2/2/2", "3//3", "a", "1/"]),
                                                       max_size=5)),
    st.sampled_from(["# comment", "", "o thing", "l 1 2", "nv 0 0 0", "vn 0 0 1", "usemtl m"]),
    st.text(max_size=20),
)


@SETTINGS
@given(lines=st.lists(obj_lines, max_size=14), validate=st.booleans())
def test_random_obj_text(lines, validate):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "m.obj")
        with open(path, "w", encoding="utf-8") as f:
            f.write("\n".join(lines))
        loads_or_value_error(lambda: load_obj(path, validate=validate))


tables = st.one_of(values, st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=0, max_size=6),
                                    min_size=0, max_size=7))


@SETTINGS
@given(document=st.one_of(values, st.fixed_dictionaries({}, optional={"density": values, "stretching": tables,
                                                                       "bending": tables, "other": values})),
       raw=st.booleans(), junk=st.text(max_size=30))
def test_random_material_json(document, raw, junk):
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "m.json")
        with open(path, "w", encoding="utf-8") as f:
            f.write(junk if raw else json.dumps(document))
        loads_or_value_error(lambda: load_material_json(path))


def test_the_fuzzers_reach_valid_documents():
    # the mutation test starts from documents that load: a failure there is the mutation's, not the base's
    for document in DOCUMENTS.values():
        scene_from_toml(dump(document), base_dir=SCENES_DIR)
    with pytest.raises(ValueError):
        scene_from_toml(dump({"name": "x"}))
