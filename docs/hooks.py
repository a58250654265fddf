"""mkdocs hook: include repository Markdown files as site pages and keep their links valid.

A page whose Markdown contains ``<!-- notebook: PATH.ipynb -->`` gets the executed notebook
(code, printed output, figures) converted to Markdown in its place. A page whose Markdown
contains ``<!-- include: PATH -->`` (``PATH`` relative to the repository
root) gets that file's text in its place. Relative links in every page are then resolved
against the file they were written in (the included file, or the page's own file under
``docs/``): links to files that are site pages (``docs/...`` or one of :data:`PAGES`) are
rewritten to the page, and links to other repository files (scripts, folders, ``mkdocs.yml``)
become plain text, so the same Markdown works on GitHub and on the site.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = "docs"

#: repository Markdown files included as site pages -> their page under docs/
PAGES = {
    "README.md": "index.md",
    "CONTRIBUTING.md": "contributing.md",
    "benchmarks/README.md": "benchmarks.md",
    "experiments/README.md": "experiments.md",
}

# executed notebooks shown as pages (docs/notebooks/NAME.md holds the directive)
PAGES.update({f"notebooks/{p.stem}.ipynb": f"notebooks/{p.stem}.md"
              for p in (ROOT / DOCS / "notebooks").glob("*.md") if p.stem != "index"})

_INCLUDE = re.compile(r"<!--\s*include:\s*(\S+)\s*-->")
_NOTEBOOK = re.compile(r"<!--\s*notebook:\s*(\S+)\s*-->")
_LINK = re.compile(r"(!?)\[([^\]\n]*)\]\(([^)\s]+)\)")


def _rewrite_links(text: str, source: str, page: str) -> str:
    """Rewrite the relative links of ``text`` (written in repository file ``source``) for the
    site page ``page`` (path under docs/)."""
    src_dir = posixpath.dirname(source)
    page_dir = posixpath.dirname(page)

    def fix(m: re.Match) -> str:
        bang, label, target = m.groups()
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
            return m.group(0)  # URL, anchor or absolute path
        path, _, anchor = target.partition("#")
        repo_path = posixpath.normpath(posixpath.join(src_dir, path))
        if repo_path in PAGES:
            doc = PAGES[repo_path]
        elif repo_path.startswith(DOCS + "/"):
            doc = repo_path[len(DOCS) + 1:]
        else:
            return label if not bang else f"`{repo_path}`"  # not on the site: plain text
        rel = posixpath.relpath(doc, page_dir or ".")
        return f"{bang}[{label}]({rel}{'#' + anchor if anchor else ''})"

    # leave fenced code blocks alone
    parts = re.split(r"(^(?:```|~~~).*?^(?:```|~~~)[^\n]*$)", text, flags=re.MULTILINE | re.DOTALL)
    return "".join(p if i % 2 else _LINK.sub(fix, p) for i, p in enumerate(parts))


def _notebook_markdown(path: str) -> str:
    """An executed ``.ipynb`` as Markdown (nbconvert), its figures inlined as data URIs."""
    import base64

    import nbformat
    from nbconvert import MarkdownExporter

    nb = nbformat.read(ROOT / path, as_version=4)
    nb.metadata.setdefault("language_info", {"name": "python"})  # highlight the code cells
    body, resources = MarkdownExporter().from_notebook_node(nb)
    for name, data in resources.get("outputs", {}).items():
        mime = "image/svg+xml" if name.endswith(".svg") else f"image/{name.rsplit('.', 1)[-1]}"
        uri = f"data:{mime};base64,{base64.b64encode(data).decode()}"
        body = body.replace(f"]({name})", f"]({uri})")
    return body


def on_page_markdown(markdown: str, page, config, files) -> str:
    page_path = page.file.src_uri  # e.g. "index.md", "api/curves.md"
    nb = _NOTEBOOK.search(markdown)
    if nb is not None:
        markdown = markdown[: nb.start()] + _notebook_markdown(nb.group(1)) + markdown[nb.end():]
    m = _INCLUDE.search(markdown)
    if m is None:
        return _rewrite_links(markdown, f"{DOCS}/{page_path}", page_path)
    included = m.group(1)
    text = (ROOT / included).read_text(encoding="utf-8")
    text = _rewrite_links(text, included, page_path)
    own = _rewrite_links(markdown[: m.start()], f"{DOCS}/{page_path}", page_path)
    rest = _rewrite_links(markdown[m.end():], f"{DOCS}/{page_path}", page_path)
    return own + text + rest
