"""Sphinx configuration of warpcloth's documentation: ``sphinx-build -W docs docs/_build/html``.

Pages are Markdown (MyST); the API reference is autodoc over the docstrings (Google style, read by napoleon).
"""

import importlib.util
import re

project = "warpcloth"
author = "the warpcloth authors"
copyright = "2026, the warpcloth authors"

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

html_theme = "furo"
html_title = "warpcloth"
html_static_path = ["_static"]  # the pictures of cloth (make_pictures.py regenerates them)

myst_heading_anchors = 3  # [text](page.md#a-heading) links
myst_enable_extensions = ["colon_fence"]

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True}
# Optional dependencies: the reference builds without them (their modules import them lazily or at the top).
autodoc_mock_imports = [name for name in ("torch", "ray") if importlib.util.find_spec(name) is None]
napoleon_google_docstring = True
napoleon_numpy_docstring = False

_CODE = re.compile(r"(``.*?``|`[^`]*`)")


def _escape_bars(app, what, name, obj, options, lines):
    """Docstrings write norms as |x|, which reStructuredText reads as a substitution: escape bars outside code."""
    for i, line in enumerate(lines):
        if "|" in line and not line.lstrip().startswith(("|", "+")):
            parts = _CODE.split(line)
            lines[i] = "".join(p if k % 2 else p.replace("|", r"\|") for k, p in enumerate(parts))


def _no_inline_types(app, what, name, obj, options, lines):
    """Napoleon reads an attribute docstring's first line as ``type: description``; here the text before a colon is
    description (``Counters over this simulator's life: ...``), so give napoleon an empty type."""
    if what in ("attribute", "data", "property") and lines:
        lines[0] = ": " + lines[0]


def setup(app):
    app.connect("autodoc-process-docstring", _no_inline_types, priority=400)  # before napoleon (500)
    app.connect("autodoc-process-docstring", _escape_bars)
