"""The ``seqat`` command line (DESIGN.md "Command line"): ``app``, built from one Typer
sub-app per stage (simulate, run / watch / feed, bench, reference, report, dsm / ortho, serve).

Commands only parse arguments, call one stage function and print its typed summary.
Exit codes: 0 success; 2 bad input or configuration (any :class:`~seqat.errors.SeqatError`,
one line ``seqat: error: <message>`` on stderr, and usage errors); 1 anything else (a one-line
message; the traceback with ``--debug`` or ``SEQAT_DEBUG=1``). Stages write their outputs
atomically, so a failed command leaves nothing half-written.
"""

from __future__ import annotations

from typing import Annotated

import typer

from pipeline.cli import bench, ortho, process, reference, report, run, serve, simulate
from pipeline.cli.common import OPTIONS, help_paragraphs, package_version, show_flags_as_flags

show_flags_as_flags()
app = typer.Typer(
    name="seqat",
    help="Sequential aerial triangulation of UAV image sequences.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"seqat {package_version()}")
        raise typer.Exit(0)


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks of internal errors.")]
    = False,
    version: Annotated[bool, typer.Option(
        "--version", help="Print the version (seqat X.Y.Z) and exit.", callback=_print_version,
        is_eager=True)] = False,
) -> None:
    """Sequential aerial triangulation of UAV image sequences."""
    OPTIONS.debug = debug


for _sub in (simulate, run, process, bench, reference, report, ortho, serve):
    for _command in _sub.app.registered_commands:
        _command.help = help_paragraphs(_command.callback)
    app.add_typer(_sub.app)
