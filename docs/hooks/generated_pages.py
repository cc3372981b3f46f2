"""MkDocs hook: pages generated from the code at build time, so they cannot drift from it.

- ``reference/cli.md``: every ``dm2`` command and option, from the typer app itself;
- ``architecture.md``: the repository's ``ARCHITECTURE.md``, the one copy of that text.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]


def cli_reference() -> str:
    import typer
    from typer.cli import get_docs_for_click

    from dm2.cli.main import app

    command = typer.main.get_command(app)
    ctx = typer.Context(command)
    body = get_docs_for_click(obj=command, ctx=ctx, name="dm2", title="Command reference")
    note = ("\n\n_This page is generated from the `dm2` command itself when the site is built; "
            "`dm2 COMMAND --help` prints the same._\n")
    return body.replace("\n", note, 1) if "\n" in body else body + note


def architecture() -> str:
    return (ROOT / "ARCHITECTURE.md").read_text(encoding="utf-8")


def on_files(files, config):
    files.append(File.generated(config, "reference/cli.md", content=cli_reference()))
    files.append(File.generated(config, "architecture.md", content=architecture()))
    return files
