"""``warpcloth.kernels`` when warpcloth is imported from a source tree (imported first by ``warpcloth/__init__.py``).

An installed wheel has ``warpcloth/kernels/`` inside the package: pyproject.toml maps the checkout's top-level
``kernels/`` there. In a checkout the two directories are siblings, so where ``./warpcloth`` comes first on
``sys.path`` (the checkout's root is the current directory, or holds the script being run) it shadows any installed
copy and nothing would find the kernels. Importing this module registers the sibling ``kernels/`` as the
``warpcloth.kernels`` subpackage: the directory an editable install maps it to. In an installed package it does
nothing.
"""

import importlib.util
import sys
from pathlib import Path


def _register_sibling_kernels() -> None:
    package = __name__.rpartition(".")[0]
    name = f"{package}.kernels"
    here = Path(__file__).resolve().parent
    kernels = here.parent / "kernels"
    if name in sys.modules or (here / "kernels").is_dir() or not (kernels / "__init__.py").is_file():
        return
    spec = importlib.util.spec_from_file_location(
        name, kernels / "__init__.py", submodule_search_locations=[str(kernels)]
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    sys.modules[package].kernels = module  # as importing the subpackage would


_register_sibling_kernels()
