"""``seqat serve``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli.common import guarded

app = typer.Typer()


@app.command()
@guarded
def serve(
    out: Annotated[Path, typer.Argument(help="Run folder (seqat run ... --out OUT), live or "
                                             "finished.")],
    port: Annotated[int, typer.Option("--port", help="TCP port (0: any free port).",
                                      min=0, max=65535)] = 8765,
    host: Annotated[str, typer.Option(
        "--host", help="Address to listen on; 127.0.0.1 (this machine only) unless given "
                       "(0.0.0.0: every interface, e.g. a tablet on the field laptop's "
                       "network).")] = "127.0.0.1",
) -> None:
    """A local web map of a run folder: the mosaic, the cameras coloured by their posterior
    sigma, the tie points and the run's status, updated while a run goes on. Read-only."""
    from pipeline.serve.app import make_server, run_server

    served = make_server(out, host, port)
    typer.echo(f"seqat serve {out}: open {served.url} (Ctrl-C stops)", err=True)
    run_server(served)
