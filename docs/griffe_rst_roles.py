"""griffe extension for the API pages: show Sphinx-style roles of the docstrings as code.

The docstrings cross-reference with Sphinx roles (``:class:`Trajectory```,
``:func:`~phjax.motion.resample.interpolate_poses```), which Markdown would print verbatim.
This extension turns each into inline code with the name as written (``~`` keeps the last
component), before mkdocstrings renders the docstring.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|attr|data|obj|exc|const):`(~?)([^`<]+?)(?:\s*<[^>]*>)?`")


def _plain(m: re.Match) -> str:
    tilde, name = m.groups()
    return f"`{name.rsplit('.', 1)[-1] if tilde else name}`"


class RstRoles(griffe.Extension):
    """Replace Sphinx roles in every docstring by inline code."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_plain, obj.docstring.value)
