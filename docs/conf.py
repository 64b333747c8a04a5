"""
Sphinx configuration of the sb3-sera documentation (Stable-Baselines3's theme and layout).

Built offline with warnings as errors and every reference checked (``make docs``):
``sphinx-build -W --keep-going -n -b html docs docs/_build/html``. No extension fetches anything: the types of
torch, numpy, Gymnasium, PettingZoo, SB3 and the standard library are named in ``nitpick_ignore_regex`` instead of
being linked through intersphinx inventories, which would need the network.
"""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The checkout's package, as SB3's docs do, whether or not it is installed
sys.path.insert(0, str(ROOT))

import sb3_sera  # noqa: E402

# -- Project information -------------------------------------------------------------------------------------------

project = "sb3-sera"
author = "sb3-sera contributors"
copyright = "2026, sb3-sera contributors"
release = sb3_sera.__version__
version = release

# -- General configuration -----------------------------------------------------------------------------------------

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.viewcode",
    "myst_parser",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
pygments_style = "sphinx"
# Every cross-reference must resolve (``-n`` on the command line says the same)
nitpicky = True

# -- MyST (the pages written in Markdown, and the ledger's generated report) --------------------------------------------

# Anchors for headings down to level 3, so that pages can link to a section: [text](page.md#section)
myst_heading_anchors = 3

# -- autodoc ---------------------------------------------------------------------------------------------------------

autodoc_member_order = "bysource"
# Methods inherited from torch, Gymnasium or SB3 keep their own docstrings there: documenting them again here would
# copy text written for other packages (and their references into them)
autodoc_inherit_docstrings = False
autodoc_typehints = "signature"
autodoc_preserve_defaults = True

# External types are named, not linked: the build has no network to fetch their inventories
_EXTERNAL = (
    r"(torch|th|nn|np|numpy|gym|gymnasium|pettingzoo|supersuit|stable_baselines3|sb3_contrib|rl_zoo3|optuna|ray"
    r"|matplotlib|pandas|scipy|yaml|rliable|collections|pathlib|typing|types|inspect|io|os|argparse|multiprocessing"
    r"|concurrent|contextlib|dataclasses|enum|abc|signal|threading|logging|subprocess|random|functools|builtins)"
)
nitpick_ignore_regex = [
    (r"py:(class|func|meth|attr|data|exc|obj|mod)", _EXTERNAL + r"(\..*)?"),
    # SB3's type aliases and classes as its own string annotations name them (``"VecEnv"``, ``"BaseCallback"``)
    (r"py:class", r"(VecEnv|BaseCallback|GymEnv|Schedule|MaybeCallback|PyTorchObs|TensorDict)"),
    # TypeVars that type ``self`` and generic returns (SB3's ``SelfSAC`` pattern), not documented objects
    (r"py:class", r"sb3_sera\..*\.(Self\w+|InitT|_Output|_\w+)"),
    # A parameterized builtin as an annotation names its origin alone
    (r"py:class", r"(dict|list|tuple|set|type|frozenset)\[.*"),
]

# -- HTML output -----------------------------------------------------------------------------------------------------

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-sera {release}"
# The sidebar expands the page shown (the theme's default): expanding every page's entries on each of the site's
# hundred-odd pages, the API reference's objects among them, took half the build (105 s of CPU against 51 s)
html_theme_options = {"navigation_depth": 3, "collapse_navigation": True}
html_show_sourcelink = False
# Wrapped table cells and a wider page for the ledger's tables
html_static_path = ["_static"]
html_css_files = ["sb3_sera.css"]

# -- Generated pages -------------------------------------------------------------------------------------------------

#: Markdown written by a study whose headings start at level 3 (python -m sera_study.theory writes the
#: tables of docs/results/theory/): each gets a page title and a section heading above them when it is read
UNTITLED_TABLES = {
    "results/theory/target_estimators": "# The target estimators: every table\n\n## The sweeps and SERA's diagnostics\n\n",
}


def _add_titles(app, docname: str, source: list[str]) -> None:
    if docname in UNTITLED_TABLES:
        source[0] = UNTITLED_TABLES[docname] + source[0]


def setup(app) -> None:
    app.connect("source-read", _add_titles)
