"""A griffe extension for the API reference: the docstrings use a few reStructuredText constructs
(``:class:`~a.b.C```, ``:math:`x```, ``.. math::`` blocks) that Markdown does not know; this turns
them into Markdown code before mkdocstrings renders the docstrings (the source is not changed). It also
reads the ``#:`` comments above a module or class attribute (Sphinx's attribute docs, which griffe does
not read) as the attribute's docstring."""

from __future__ import annotations

import re
from typing import Any

import griffe

#: :role:`target` or :role:`~a.b.target` (Sphinx roles): the target as code; ``~`` keeps its last part
_ROLE = re.compile(r":(?:class|func|meth|attr|data|mod|obj|exc|const|ref|py:\w+):`(~?)([^`]+)`")
_MATH = re.compile(r":math:`([^`]+)`")
_BLOCK = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<first>.*)$")


def _role(m: re.Match) -> str:
    target = m.group(2).strip()
    if m.group(1):
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def _math_blocks(text: str) -> str:
    """``.. math::`` directives (the formula on the same line and/or the indented lines below) as code
    blocks."""
    lines, out, i = text.splitlines(), [], 0
    while i < len(lines):
        m = _BLOCK.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent = m.group("indent")
        body = [m.group("first").strip()] if m.group("first").strip() else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)):
            body.append(lines[i].strip())
            i += 1
        while body and not body[-1]:
            body.pop()
        out += ["", f"{indent}```text", *[f"{indent}{b}" for b in body], f"{indent}```", ""]
    return "\n".join(out)


def rst_to_markdown(text: str) -> str:
    """The docstring ``text`` with Sphinx roles, inline math and math blocks as Markdown code."""
    text = _math_blocks(text)
    text = _MATH.sub(lambda m: f"`{m.group(1)}`", text)
    return _ROLE.sub(_role, text)


def comment_doc(lines: list[str], lineno: int) -> str | None:
    """The ``#:`` comment lines right above line ``lineno`` (1-based) of ``lines``, without the markers."""
    doc, i = [], lineno - 2
    while i >= 0 and lines[i].lstrip().startswith("#:"):
        doc.insert(0, lines[i].lstrip()[2:].strip())
        i -= 1
    return "\n".join(doc) or None


class RstRoles(griffe.Extension):
    """Rewrite each docstring as it is loaded (:func:`rst_to_markdown`); give an attribute without a
    docstring its ``#:`` comment (:func:`comment_doc`)."""

    def on_instance(self, *, node: Any, obj: griffe.Object, agent: Any, **kwargs: Any) -> None:
        if obj.docstring is None and obj.is_attribute and obj.lineno:
            try:
                lines = obj.module.lines
            except Exception:  # noqa: BLE001  (no source: nothing to read)
                lines = []
            text = comment_doc(lines, obj.lineno) if lines else None
            if text:
                obj.docstring = griffe.Docstring(text, lineno=obj.lineno, parent=obj)
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
