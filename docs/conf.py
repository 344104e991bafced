"""Sphinx configuration of the dolfinx_lopinf documentation.

    make docs            # sphinx-build -W (warnings are errors) -> docs/_build/html
    make docs-figures    # the benchmark tables and figures from results/*/metrics.json

The pages are Markdown (myst-parser); the API pages come from the docstrings (autodoc +
napoleon, Google style). The tables and figures under docs/generated/ are written by
``python -m dolfinx_lopinf.studies.report --docs docs/generated`` from the demos' results and
committed; building the pages runs no demo.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's package, not another installed copy
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
os.environ.setdefault("MPLBACKEND", "Agg")

import dolfinx_lopinf  # noqa: E402  (imports dolfinx_solver before dolfinx with the PyPI wheel)

project = "dolfinx_lopinf"
author = "the dolfinx_lopinf developers"
copyright = "2026, the dolfinx_lopinf developers"
release = dolfinx_lopinf.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx_copybutton",
]

source_suffix = {".md": "markdown"}
root_doc = "index"
# docs/generated/*.md are included by the pages (``{include}``), not pages of their own
exclude_patterns = ["_build", "generated/*.md", "generated/**/README.md", "Thumbs.db", ".DS_Store"]

myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_attr_annotations = True

html_theme = "furo"
html_title = f"dolfinx_lopinf {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]
html_show_sourcelink = False
copybutton_prompt_text = r">>> |\.\.\. |\$ "
copybutton_prompt_is_regexp = True

# Every warning is an error (`make docs` passes -W); nothing is silenced here except what a
# Markdown page cannot avoid: none so far.
suppress_warnings: list[str] = []
