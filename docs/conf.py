"""Sphinx's configuration for labcal's documents: Markdown pages read through MyST, built as one
site (`sphinx-build -W -b html docs docs/_build`); CI builds it with warnings as errors."""

project = "labcal"
author = "labcal's developers"
extensions = ["myst_parser"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_heading_anchors = 3  # links to a page's sections by their titles
html_theme = "alabaster"
html_static_path: list[str] = []
