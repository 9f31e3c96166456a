"""Output folders: never an input, never someone else's folder (docs/formats.md, *Output folder*).

A folder seqat writes results into is *claimed* with a marker file (as ``seqat simulate``
recognises its flight folders by ``flight.yaml``): an absent or empty folder may be claimed,
a folder with the marker is one seqat made and may be written again, and any other non-empty
folder is refused, so files the user keeps there (an ``eop.csv``, a ``nav.csv``) are never
replaced. An output folder must not be, contain or lie inside any input of the command.

Writing errors at the output boundary (read-only folder, ``/proc``, a folder where a file is
to be written) are the user's to fix: :func:`output_errors` turns them into one-line
:class:`~seqat.errors.InputDataError` s naming the user's path.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

from seqat.errors import InputDataError

#: Marker file of a run folder (``seqat run`` / ``watch``); written when the folder is claimed.
RUN_MARKER = ".seqat-run"
#: Files that also mark a run folder written before the marker existed (a finished run, an
#: interrupted one).
LEGACY_RUN_MARKERS = ("run.json", "journal/journal.log")


def _resolved(path: Path) -> Path:
    return Path(os.path.abspath(path)).resolve()


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def check_not_input(out: Path | str, inputs: Iterable[Path | str | None], *,
                    option: str = "--out") -> None:
    """Refuse an output path that is, contains or lies inside one of ``inputs``.

    Raises
    ------
    InputDataError
        Naming the output and the input it collides with.
    """
    out_r = _resolved(Path(out))
    for given in inputs:
        if given is None:
            continue
        inp = _resolved(Path(given))
        if out_r == inp:
            how = "is"
        elif _inside(out_r, inp) and inp.is_dir():
            how = "lies inside"
        elif _inside(inp, out_r):
            how = "contains"
        else:
            continue
        raise InputDataError(f"{out}: {option} {how} the input {given}; seqat never writes "
                             "over or into its inputs (choose an output outside them)")


def is_marked(folder: Path, marker: str = RUN_MARKER,
              legacy: Iterable[str] = LEGACY_RUN_MARKERS) -> bool:
    """Whether ``folder`` holds seqat's marker (or a legacy marker file)."""
    return any((folder / name).is_file() for name in (marker, *legacy))


def check_output_folder(out: Path | str, inputs: Iterable[Path | str | None] = (), *,
                        marker: str = RUN_MARKER,
                        legacy: Iterable[str] = LEGACY_RUN_MARKERS,
                        what: str = "run folder") -> None:
    """Refuse an output folder that is an input, a file, or a non-empty folder seqat did not
    make (no ``marker``).

    Raises
    ------
    InputDataError
    """
    out = Path(out)
    check_not_input(out, inputs)
    if not out.exists():
        return
    if not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    try:
        empty = not any(out.iterdir())
    except OSError as err:
        raise InputDataError(f"{out}: cannot read the output folder: "
                             f"{err.strerror or err}") from err
    if empty or is_marked(out, marker, legacy):
        return
    raise InputDataError(f"{out}: exists, is not empty and is not a seqat {what} (no {marker}); "
                         "refusing to write into it (choose a new or empty folder)")


def claim_output_folder(out: Path | str, inputs: Iterable[Path | str | None] = (), *,
                        marker: str = RUN_MARKER, what: str = "run folder") -> list[Path]:
    """Check ``out`` (:func:`check_output_folder`), create it and write the marker.

    Returns
    -------
    list[Path]
        The folders created, deepest first (for a caller that removes them on failure).
    """
    out = Path(out)
    check_output_folder(out, inputs, marker=marker, what=what)
    created: list[Path] = []
    probe = out
    while not probe.exists():
        created.append(probe)
        probe = probe.parent
    with output_errors(out):
        out.mkdir(parents=True, exist_ok=True)
        mark = out / marker
        if not mark.exists():
            mark.write_text("written by seqat: this folder holds seqat's results and may be "
                            "replaced by seqat\n", encoding="utf-8")
    return created


def release_output_folder(out: Path, created: list[Path], marker: str = RUN_MARKER) -> None:
    """Undo :func:`claim_output_folder` after a failure: the marker and the folders it made
    go, when nothing else was written into them."""
    if not created:
        return
    with contextlib.suppress(OSError):
        if [p.name for p in out.iterdir()] == [marker]:  # else seqat's files are in it
            (out / marker).unlink()
    for folder in created:
        with contextlib.suppress(OSError):
            folder.rmdir()


def describe_os_error(err: OSError) -> str:
    return err.strerror or str(err)


@contextlib.contextmanager
def output_errors(path: Path | str, what: str = "cannot write") -> Iterator[None]:
    """Turn an :class:`OSError` raised while writing into ``path`` into an InputDataError
    naming ``path`` (the user's path, never a temporary file)."""
    try:
        yield
    except InputDataError:
        raise
    except IsADirectoryError as err:
        raise InputDataError(f"{path}: {what}: is a folder (give a file name)") from err
    except OSError as err:
        raise InputDataError(f"{path}: {what}: {describe_os_error(err)}") from err
