"""MkDocs hooks: the command-line reference from the argparse parsers; Sphinx roles in docstrings.

A page line ``<!-- cli-reference -->`` (docs/reference/cli.md) becomes, for ``crfdepth`` and
each of its sub-commands, a heading and the ``--help`` text, formatted at a fixed width so
the page does not depend on the terminal that builds the site. The width (72 columns) fits the
theme's text column on a laptop; on a narrower window the block wraps its lines
(docs/stylesheets/cli.css) instead of hiding them behind a scrollbar.

The library's docstrings cite objects as Sphinx roles (``:func:`~crfdepth.api.complete_depth```),
which mkdocstrings renders as ``:func:`` and a code span. The hook drops the role, shortens a
``~`` path to its last name, and links a ``crfdepth.`` path to its entry where the site has one
(an optional autorefs link: plain code where it has none).
"""

from __future__ import annotations

import argparse
import functools
import html
import re

MARKER = "<!-- cli-reference -->"
WIDTH = 72  # columns of the help text
# A Sphinx role as rendered from a docstring: ``:class:<code>~crfdepth.model.CRFDepth</code>``.
ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj):<code>(?P<tilde>~?)(?P<path>[\w.]+)</code>")


def _help(parser: argparse.ArgumentParser) -> str:
    """``parser``'s ``--help`` text at :data:`WIDTH` columns, without colour; ``parser`` is left as it was."""
    formatter_class = parser.formatter_class
    parser.formatter_class = functools.partial(formatter_class, width=WIDTH)
    color = getattr(parser, "color", None)  # Python 3.14+ may colour help on a terminal
    if color is not None:
        parser.color = False
    try:
        return parser.format_help().rstrip()
    finally:
        parser.formatter_class = formatter_class
        if color is not None:
            parser.color = color


def commands() -> list[tuple[str, argparse.ArgumentParser]]:
    """(command, parser) of ``crfdepth`` and of each sub-command, in ``crfdepth --help``'s order."""
    from crfdepth.cli import build_parser

    parser = build_parser()
    found = [(parser.prog, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found += [(sub.prog, sub) for sub in action.choices.values()]
    return found


def cli_reference() -> str:
    """The Markdown that replaces :data:`MARKER`: a level-2 heading and a ``pre.cli-help`` block per command."""
    return "\n\n".join(f'## `{name}`\n\n<pre class="cli-help"><code>{html.escape(_help(parser))}</code></pre>'
                       for name, parser in commands())


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_reference())
    return markdown


def _object_reference(match: re.Match) -> str:
    """The code span (an optional cross-reference for a ``crfdepth.`` path) of a :data:`ROLE` match."""
    path = match["path"]
    text = path.rsplit(".", 1)[-1] if match["tilde"] else path
    if not path.startswith("crfdepth."):
        return f"<code>{text}</code>"  # a name relative to the docstring's module: no target to name
    return f'<autoref identifier="{path}" optional><code>{text}</code></autoref>'


def on_page_content(html: str, page, config, files) -> str:
    if not page.file.src_uri.startswith("reference/"):  # docstrings are rendered on the reference pages only
        return html
    html = ROLE.sub(_object_reference, html)
    return html.replace("::</p>", ":</p>")  # reStructuredText's literal-block marker before a code block
