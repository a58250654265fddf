"""griffe extension for the API pages: the reStructuredText bits of the docstrings as Markdown.

* Sphinx roles (``:class:`Trajectory```, ``:func:`~phjax.motion.resample.interpolate_poses```),
  which Markdown would print verbatim, become inline code with the name as written (``~``
  keeps the last component).
* Two-column RST simple tables (``====  ====`` borders, no header) become bullet lists
  ``- first: second``.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|attr|data|obj|exc|const):`(~?)([^`<]+?)(?:\s*<[^>]*>)?`")


_BORDER = re.compile(r"^( *)(=+)( +)=+ *$")


def _simple_tables(text: str) -> str:
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = _BORDER.match(lines[i])
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() and
                    _BORDER.match(lines[j])), None) if m else None
        if m is None or end is None:
            out.append(lines[i])
            i += 1
            continue
        indent, split = len(m.group(1)), len(m.group(1)) + len(m.group(2)) + len(m.group(3))
        items: list[list[str]] = []
        for row in lines[i + 1:end]:
            first, second = row[indent:split].strip(), row[split:].strip()
            if first:
                items.append([first, second])
            elif items and second:
                items[-1][1] += " " + second
        out += [" " * indent + f"- {a}: {b}" for a, b in items]
        i = end + 1
    return "\n".join(out)


def _plain(m: re.Match) -> str:
    tilde, name = m.groups()
    return f"`{name.rsplit('.', 1)[-1] if tilde else name}`"


class RstRoles(griffe.Extension):
    """Rewrite Sphinx roles and simple tables in every docstring (see the module docstring)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _simple_tables(_ROLE.sub(_plain, obj.docstring.value))
