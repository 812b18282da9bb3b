"""The documentation site (``mkdocs.yml``, ``docs/``): it builds with ``mkdocs build --strict`` (every nav entry
exists, every link resolves, every API page renders from the docstrings), every study's
``experiments/<study>/README.md`` is a page of it, and the griffe extension turns the docstrings'
reStructuredText roles and math into Markdown. Needs the ``docs`` extra (``pip install -e ".[docs]"``);
skipped without MkDocs."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

mkdocs = pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
pytest.importorskip("mkdocstrings", reason="the docs extra is not installed (pip install -e '.[docs]')")
pytest.importorskip("material", reason="the docs extra is not installed (pip install -e '.[docs]')")
pytest.importorskip("mkdocs_include_markdown_plugin", reason="the docs extra is not installed (pip install -e '.[docs]')")

#: modules whose API page the site must have (``::: <module>`` somewhere under docs/reference/)
API_MODULES = ("dslearn.api", "dslearn.episodes", "dslearn.network", "dslearn.models.base", "dslearn.methods.base",
               "dslearn.fusion.strategies", "dslearn.fusion.weights", "dslearn.filters.information",
               "dslearn.metrics.positions")


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built with ``mkdocs build --strict`` into a temporary folder (from an unrelated folder)."""
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                          "-d", str(out)], cwd=out.parent, env=env, capture_output=True, text=True, timeout=300)
    # a failed build says why: its WARNING/ERROR lines first (the cause; strict mode aborts at the end), then the tail
    causes = [ln for ln in (res.stdout + res.stderr).splitlines() if re.search(r"\b(WARNING|ERROR)\b", ln)]
    assert res.returncode == 0, "\n".join(causes[:50]) + "\n...\n" + res.stderr[-2000:]
    return out


def _text(page: Path) -> str:
    return re.sub(r"<[^>]+>", "", page.read_text(encoding="utf-8"))


def test_strict_build_renders_the_api(site):
    # the docstrings reached the pages: a function, a dataclass field and a protocol method of the named modules
    api = _text(site / "reference" / "api" / "index.html")
    assert "yu_study" in api and "build_study" in api
    # a module attribute documented by a "#:" comment (read by docs/griffe_rst.py)
    assert "SHORT_KEYS" in api and "shorthand keyword -&gt; configuration key of" in api
    episodes = _text(site / "reference" / "episodes" / "index.html")
    assert "ScenarioSpec" in episodes and "num_agents" in episodes and "terrain_altitude" in episodes
    methods = _text(site / "reference" / "methods" / "index.html")
    assert "require" in methods and "fits" in methods
    # no reST role or math directive is left as raw text anywhere
    for page in (site / "reference").rglob("index.html"):
        raw = page.read_text(encoding="utf-8")
        assert not re.search(r":(class|func|meth|attr|data|mod|math):`", raw), page
        assert ".. math::" not in raw, page


def test_every_study_readme_is_a_page(site):
    # each experiments/<study>/README.md is included whole: its first and last non-empty lines are on the page
    readmes = sorted(ROOT.glob("experiments/*/README.md"))
    assert readmes
    for readme in readmes:
        study = readme.parent.name
        page = DOCS / "reproductions" / f"{study}.md"
        assert page.is_file(), f"{study}: add docs/reproductions/{study}.md (and its nav entry in mkdocs.yml)"
        built = site / "reproductions" / study / "index.html"
        assert built.is_file(), f"{study}: its page is not in the built site"
        lines = [ln for ln in readme.read_text(encoding="utf-8").splitlines() if ln.strip()]
        html = _text(built)
        first = lines[0].lstrip("# ").strip()
        assert first.split()[0] in html, study
        last_words = re.findall(r"[A-Za-z]{4,}", lines[-1])
        assert all(w in html for w in last_words), (study, last_words)


def test_the_named_modules_have_api_pages():
    pages = "\n".join(p.read_text(encoding="utf-8") for p in (DOCS / "reference").glob("*.md"))
    documented = set(re.findall(r"^::: ([\w.]+)\s*$", pages, re.M))
    assert set(API_MODULES) <= documented, set(API_MODULES) - documented
    for mod in documented:
        assert importlib.util.find_spec(mod) is not None, mod


#: the app around the library: command-line entry points, reports, the config validation layer, progress output
#: and developer tools; the how-to pages and the README document them by their commands and options
APP = ("dslearn.run", "dslearn.app", "dslearn.bench", "dslearn.report", "dslearn.reports", "dslearn.schemas",
       "dslearn.progress", "dslearn.callbacks", "dslearn.conf_paths", "dslearn.search_path", "dslearn.tools",
       "dslearn.train_lstm")


def test_every_library_module_has_an_api_page():
    """Every public module of the library (not the app, above) is rendered on a page of docs/reference/."""
    pages = "\n".join(p.read_text(encoding="utf-8") for p in (DOCS / "reference").glob("*.md"))
    documented = set(re.findall(r"^::: ([\w.]+)\s*$", pages, re.M))
    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts) for p in (ROOT / "dslearn").rglob("*.py")
               if not any(part.startswith("_") for part in p.relative_to(ROOT).parts)}
    library = {m for m in modules if not any(m == a or m.startswith(a + ".") for a in APP)}
    assert library - documented == set(), sorted(library - documented)


def test_no_machine_paths_in_the_docs():
    for page in [*DOCS.rglob("*.md"), ROOT / "mkdocs.yml"]:
        text = page.read_text(encoding="utf-8")
        assert not re.search(r"(?<![\w.])/(work|tmp|home|root)/", text), page


def _ext():
    spec = importlib.util.spec_from_file_location("griffe_rst", DOCS / "griffe_rst.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_rst_roles_and_math_become_markdown():
    rst = _ext().rst_to_markdown
    assert rst("see :class:`~dslearn.episodes.ScenarioSpec` and :func:`dslearn.api.run`.") == \
        "see `ScenarioSpec` and `dslearn.api.run`."
    assert rst(r"noise :math:`\eta \sim \mathcal N(0, Q)` here") == r"noise `\eta \sim \mathcal N(0, Q)` here"
    assert rst(":meth:`Method.fits`, :data:`MEASUREMENTS`, :attr:`~a.b.c.d`") == "`Method.fits`, `MEASUREMENTS`, `d`"
    # a math directive, the formula on its line and continued below, indented text after it kept
    text = "Intro.\n\n    .. math:: a = b\n        + c\n\n    After."
    assert rst(text) == "Intro.\n\n\n    ```text\n    a = b\n    + c\n    ```\n\n    After."
    # a directive with the formula only on the following lines
    assert rst(".. math::\n    x_j = y\nNext") == "\n```text\nx_j = y\n```\n\nNext"
    assert rst("no roles: `code` and ``literal``") == "no roles: `code` and ``literal``"


def test_comment_docs_of_attributes():
    doc = _ext().comment_doc
    lines = ["x = 1", "#: first line", "  #: second line", "NAME = 2", "# plain comment", "OTHER = 3"]
    assert doc(lines, 4) == "first line\nsecond line"   # NAME: the two #: lines above it
    assert doc(lines, 6) is None                         # OTHER: a plain comment is not a doc
    assert doc(lines, 1) is None                         # first line of the file
