r"""Sphinx configuration of the meso-hmodel documentation site (``make docs``).

The Markdown pages of ``docs/`` are read by MyST-Parser; the API reference is generated at
build time from the docstrings (Google style, read by napoleon): ``api.md`` names the three
packages and ``autosummary`` walks their modules recursively into ``docs/_autosummary/``,
so a new or moved module needs no edit here.

Equations: MyST's ``dollarmath`` (``$...$`` inline, ``$$...$$`` display) and ``amsmath``
(``\begin{aligned}`` and the like) turn them into math nodes, which ``sphinx.ext.mathjax``
writes as ``\(...\)`` / ``\[...\]`` for MathJax. ``sphinx-mathjax-offline`` copies MathJax
into the site's ``_static/``, so neither building nor reading the site needs a network.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sphinx.ext.napoleon import _process_docstring as _napoleon_process  # noqa: E402

from warp_hcell.core.cli import quiet_warp  # noqa: E402
from warp_hcell.core.provenance import DISTRIBUTION, package_version  # noqa: E402

quiet_warp()  # autodoc imports the DEM modules: no Warp banner in the build log

project = "meso-hmodel"
author = "The meso-hmodel contributors"
copyright = "the meso-hmodel contributors, MIT licence"
release = package_version(DISTRIBUTION)
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
highlight_language = "text"  # literal blocks of docstrings and bare fences hold formulas and diagrams
templates_path = ["_templates"]

myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath", "amsmath"]

autosummary_generate = True
toc_object_entries = False
autosummary_ignore_module_all = False
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_class_signature = "separated"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_ivar = False
napoleon_use_rtype = False



def _napoleon_without_inline_types(app, what, name, obj, options, lines):
    """Napoleon on every docstring, a constant's or attribute's read like any other.

    For ``attribute``, ``data`` and ``property`` docstrings napoleon takes the text before a
    first-line colon as the type (Google's inline ``int: description``). The package's
    docstrings are prose with units (``"Deviator measure drawn: q = ... or t = q / 2."``) and
    their types come from annotations, so that text would become a "Type" field; napoleon is
    therefore told that such a docstring belongs to no particular kind of object.
    """
    _napoleon_process(app, "" if what in ("attribute", "data", "property") else what, name, obj, options, lines)


def setup(app):
    """Put ``_napoleon_without_inline_types`` in the place of napoleon's own docstring handler."""
    for listener in list(app.events.listeners["autodoc-process-docstring"]):
        if listener.handler is _napoleon_process:
            app.disconnect(listener.id)
    app.connect("autodoc-process-docstring", _napoleon_without_inline_types)


html_theme = "furo"
html_title = f"meso-hmodel {release}"
html_static_path: list[str] = []
