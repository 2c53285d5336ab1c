"""Registers a source checkout's top-level ``kernels/`` as ``warpcloth.kernels``, where the checkout's ``warpcloth/``
comes first on ``sys.path`` and would find no kernels (a wheel has them inside, per pyproject.toml); does nothing
in an installed package. Imported first by ``warpcloth/__init__.py``."""

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
