"""Sphinx configuration of warptan's documentation: ``pip install ".[docs]" && sphinx-build -W -b html docs
docs/_build/html`` (warnings are errors; CI builds it)."""

import warptan

project = "warptan"
author = "the warptan developers"
release = warptan.__version__
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.autosummary", "sphinx.ext.napoleon",
              "sphinx.ext.mathjax"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
myst_heading_anchors = 3
templates_path = ["_templates"]
exclude_patterns = ["_build"]
autosummary_generate = True
autodoc_member_order = "bysource"
autodoc_mock_imports = ["rasterio", "trimesh", "matplotlib", "rosbags", "ray"]
napoleon_google_docstring = True
napoleon_numpy_docstring = False
html_theme = "alabaster"
html_title = f"warptan {release}"
