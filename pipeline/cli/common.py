"""What every ``seqat`` command shares (DESIGN.md "Command line").

Commands only parse arguments, call one stage function and print its typed summary.
Exit codes: 0 success; 2 bad input or configuration (any :class:`~seqat.errors.SeqatError`,
one line ``seqat: error: <message>`` on stderr, and usage errors); 1 anything else (a one-line
message; the traceback with ``--debug`` or ``SEQAT_DEBUG=1``). Stages write their outputs
atomically, so a failed command leaves nothing half-written.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import os
import traceback
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, ParamSpec, TypeVar

import typer
from rich.console import Console
from rich.table import Table

from seqat.errors import ConfigError, SeqatError

if TYPE_CHECKING:
    from pipeline.run.runner import RunSummary


#: Exit code for bad input or configuration (also click's usage errors).
EXIT_BAD_INPUT = 2
#: Exit code for any other failure.
EXIT_FAILURE = 1
#: Conventional exit code after Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Environment variable that turns on tracebacks like ``--debug``.
DEBUG_ENV = "SEQAT_DEBUG"

P = ParamSpec("P")
R = TypeVar("R")


@dataclasses.dataclass(kw_only=True)
class Options:
    """Global options of the current invocation (set by the app callback)."""

    debug: bool = False


OPTIONS = Options()


def debug_enabled() -> bool:
    return OPTIONS.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0")


def one_line(text: str) -> str:
    return " ".join(text.split())


def guarded(command: Callable[P, R]) -> Callable[P, R]:
    """Map exceptions to the exit codes of the command-line contract."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except (typer.Exit, typer.Abort):
            raise
        except SeqatError as err:
            typer.echo(f"seqat: error: {one_line(str(err))}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from err
        except KeyboardInterrupt as err:
            typer.echo("seqat: interrupted", err=True)
            raise typer.Exit(EXIT_INTERRUPTED) from err
        except Exception as err:  # noqa: BLE001 - the contract: anything else exits 1
            if debug_enabled():
                traceback.print_exc()
            typer.echo(f"seqat: internal error: {type(err).__name__}: {one_line(str(err))} "
                       f"(rerun with --debug or {DEBUG_ENV}=1 for the traceback)", err=True)
            raise typer.Exit(EXIT_FAILURE) from err

    return wrapper


def choice(flag: str, value: str, choices: Iterable[str]) -> str:
    """A choice option's value, in any case (``SEQ-R``, ``Sim``): normalised to the lower-case
    choice before it is checked.

    Raises
    ------
    ConfigError
        Not one of ``choices``; the message lists them (exit 2, one line).
    """
    allowed = [str(c) for c in choices]
    normalised = value.strip().lower()
    if normalised not in allowed:
        raise ConfigError(f"{flag}: expected one of {', '.join(allowed)}, got {value!r}")
    return normalised


def package_version() -> str:
    """The installed seqat's version (package metadata), or ``unknown`` when not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("seqat")
    except PackageNotFoundError:
        return "unknown"


def help_paragraphs(command: Callable[..., object] | None) -> str | None:
    """A command's docstring as ``--help`` shows it: each paragraph on one line (the terminal
    wraps it), paragraphs kept apart. Typer's rich help keeps the docstring's line breaks in the
    command list, which breaks lines in the middle of a sentence."""
    doc = getattr(command, "__doc__", None)
    if not doc:
        return None
    paragraphs = inspect.cleandoc(doc).split("\n\n")
    return "\n\n".join(" ".join(p.split()) for p in paragraphs if p.strip())


def show_flags_as_flags() -> None:
    """Boolean flags in ``--help`` as ``--ortho``, not ``--ortho <bool>``.

    Typer 0.2x prints a type column for every option, ``<bool>`` for flags too (``--help``
    included); a flag takes no value, so its type column is left empty. Without that method
    (older Typer) nothing is changed; ``tests/pipeline/cli/test_consistency.py`` checks the
    help of every command. Idempotent.
    """
    from typer.core import TyperOption

    original = getattr(TyperOption, "display_type_rich", None)
    if original is None or getattr(original, "_seqat_flags", False):
        return

    def display_type_rich(self: TyperOption, ctx: object) -> str | None:
        if self.is_flag and not self.count:
            return None
        return original(self, ctx)

    display_type_rich._seqat_flags = True  # type: ignore[attr-defined]
    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]


def console() -> Console:
    return Console()


#: Display formats: metres to the millimetre, degrees to 1e-4, anything else 6 digits.
METRE_FORMAT = ".3f"
DEGREE_FORMAT = ".4f"
GENERAL_FORMAT = ".6g"


def fmt(value: object, spec: str = GENERAL_FORMAT) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else format(value, spec)
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return "  ".join(fmt(v, spec) for v in value)
    return str(value)


def table(title: str, rows: list[tuple[str, str]]) -> Table:
    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    for key, value in rows:
        table.add_row(key, value)
    return table


def stats_ms(t: object) -> str:
    return (f"{t.median_ms:.1f} / {t.p95_ms:.1f} / {t.max_ms:.1f}")  # type: ignore[attr-defined]


def run_rows(summary: RunSummary, final_only: bool = False) -> list[tuple[str, str]]:
    """The table ``seqat run`` and ``seqat watch`` print."""
    t = summary.update_ms
    rows = [
        ("method", summary.method.value + (" (final only)" if final_only else "")),
        ("images / points / observations",
         f"{summary.n_images} / {summary.n_points} / {summary.n_observations}"),
        ("sigma0 (redundancy)", f"{fmt(summary.sigma0, '.4f')} ({summary.redundancy})"),
        ("update ms median / p95 / max", stats_ms(t)),
    ]
    ts = summary.sequential_update_ms
    if math.isfinite(ts.median_ms):
        rows.append(("  sequential stage only", stats_ms(ts)))
    if summary.sequential_refine_ms is not None:  # once each estimate was out
        rows.append(("  refinement after the update (re-linearisation)",
                     stats_ms(summary.sequential_refine_ms)))
    if summary.second_start_ms is not None:  # after the updates, not in their times
        rows.append(("second starts kept / tried, ms median / p95 / max",
                     f"{summary.second_starts_kept} / {summary.second_starts_tried}, "
                     f"{stats_ms(summary.second_start_ms)}"))
    if summary.latency_ms is not None:
        rows.append(("latency ms median / p95 / max", stats_ms(summary.latency_ms)))
    b = summary.budget
    if b is not None:
        limit = "batch" if b.budget_ms is None else f"{b.budget_ms:.0f} ms"
        features = "" if b.final_features is None else f", features {b.final_features}"
        rows.append((f"budget ({b.mode}) / over / changes",
                     f"{limit} / {b.images_over_budget} images / "
                     f"{len(b.events)} (final threshold {b.final_threshold:g}{features})"))
    if summary.replayed:
        rows.append(("replayed from the journal", f"{summary.replayed} images"))
    if summary.skipped:
        rows.append(("skipped", f"{len(summary.skipped)} images (run.json skipped)"))
    rows += [
        ("total update / wall", f"{t.total_ms / 1e3:.2f} s / {summary.wall_s:.2f} s"),
    ]
    acc = summary.accuracy
    if acc is not None:
        rows += [
            ("EOP position RMSE x y z (m)", fmt(acc.pos_rmse_m, METRE_FORMAT)),
            ("  GPS/INS input (m)", fmt(acc.nav_pos_rmse_m, METRE_FORMAT)),
            ("EOP attitude RMSE ω φ κ (deg)", fmt(acc.att_rmse_deg, DEGREE_FORMAT)),
            ("  GPS/INS input (deg)", fmt(acc.nav_att_rmse_deg, DEGREE_FORMAT)),
            ("ground point RMSE x y z (m)", fmt(acc.gp_rmse_m, METRE_FORMAT)),
        ]
    rows.append(("results", str(summary.out_dir)))
    return rows
