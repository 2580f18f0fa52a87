"""The docs site writes equations as math: MyST's dollarmath and amsmath, rendered by MathJax."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "docs" / "model.md"


def _conf_value(name: str):
    tree = ast.parse((ROOT / "docs" / "conf.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"docs/conf.py sets no {name}")


def test_conf_enables_dollar_math_and_mathjax():
    assert {"dollarmath", "amsmath"} <= set(_conf_value("myst_enable_extensions"))
    assert "sphinx.ext.mathjax" in _conf_value("extensions")
    assert "sphinx-mathjax-offline" in _conf_value("extensions")  # MathJax from the site, not a CDN


def _planar_sections() -> str:
    """docs/model.md up to its section 14 (sections 1-13: the planar H-model)."""
    text = MODEL.read_text()
    return text[:text.index("## 14.")]


def test_planar_model_equations_are_math_not_ascii_blocks():
    markdown_it = pytest.importorskip("markdown_it")
    dollarmath = pytest.importorskip("mdit_py_plugins.dollarmath")
    md = markdown_it.MarkdownIt("commonmark").enable("table").use(dollarmath.dollarmath_plugin)
    tokens = md.parse(_planar_sections())
    display = [t for t in tokens if t.type == "math_block"]
    inline = [c for t in tokens if t.type == "inline" for c in (t.children or []) if c.type == "math_inline"]
    assert len(display) >= 10 and len(inline) >= 100
    for key in ("N_2 = N_1\\cos\\alpha + T_1\\sin\\alpha", "S_{nn} &= 4 N_1 d_1 \\cos^2\\alpha", "w(\\theta) ="):
        assert any(key in t.content for t in display), key
    ascii_blocks = [t.content for t in tokens if t.type == "code_block" and "=" in t.content]
    assert not ascii_blocks  # indented "    N2 = N1 cos(alpha) ..." blocks are gone
    prose = " ".join(c.content for t in tokens if t.type == "inline" for c in (t.children or []) if c.type == "text")
    assert not re.search(r"\b(alpha|sigma|eps|phi_g|kn|N1|T1|S_nn)\d*\b\s*=", prose)  # no ASCII formula in the text


def _conf_module():
    """docs/conf.py as a module (it imports sphinx: skipped without the docs extra)."""
    pytest.importorskip("sphinx.ext.napoleon")
    import importlib.util

    spec = importlib.util.spec_from_file_location("docs_conf", ROOT / "docs" / "conf.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("what", ["data", "attribute", "property"])
def test_api_reference_reads_a_constants_docstring_as_prose_not_as_its_type(what):
    """A first-line colon in a constant's docstring is prose: no "Type" field made of its first words."""
    from types import SimpleNamespace

    from sphinx.ext.napoleon import Config

    conf = _conf_module()
    app = SimpleNamespace(config=Config(**{k: v for k, v in vars(conf).items() if k.startswith("napoleon_")}))
    lines = ["Deviator measure drawn: q = sigma11 - sigma22 or t = q / 2."]
    conf._napoleon_without_inline_types(app, what, "homogenization.output.figures.DEVIATORS", ("q", "t"), None, lines)
    assert lines == ["Deviator measure drawn: q = sigma11 - sigma22 or t = q / 2."]
    sections = ["Run of a test.", "", "Args:", "    x: length [m]."]
    conf._napoleon_without_inline_types(app, "function", "f", None, None, sections)
    assert ":param x: length [m]." in sections  # other docstrings: napoleon as before
