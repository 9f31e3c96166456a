"""Atomic writing: files replaced whole (temp file, fsync, rename) and folders published whole.

A reader never sees a half-written file or folder, and a failed write leaves the previous
version untouched (docs/formats.md).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path

from pipeline.common.outdir import output_errors
from seqat.errors import InputDataError


def _file_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def _write_temp(folder: Path, name: str, text: str | bytes) -> Path:
    """Write ``text`` (UTF-8) or bytes to a new temporary file in ``folder`` and fsync it."""
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
    try:
        if isinstance(text, bytes):
            handle = os.fdopen(fd, "wb")
        else:
            handle = os.fdopen(fd, "w", encoding="utf-8", newline="")
        with handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, _file_mode())
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return Path(tmp)


def fsync_dir(folder: Path) -> None:
    """Make a rename inside ``folder`` durable (no-op where directories cannot be opened)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write_text(path: Path | str, text: str | bytes) -> None:
    """Replace ``path`` by ``text`` (str as UTF-8, or bytes) atomically (temp file in the
    same folder, fsync, rename).

    File system errors are InputDataErrors naming ``path`` (:func:`output_errors`).
    """
    path = Path(path)
    with output_errors(path):
        _atomic_write_text(path, text)


def _atomic_write_text(path: Path, text: str | bytes) -> None:
    if path.is_dir():
        raise InputDataError(f"{path}: is a folder; cannot write a file there")
    tmp = _write_temp(path.parent, path.name, text)
    try:
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def write_files_atomically(out_dir: Path | str,
                           files: Mapping[str, str | bytes]) -> tuple[Path, ...]:
    """Publish several files (text, or bytes such as a PDF) into ``out_dir`` together.

    All files are first written to temporary files in ``out_dir``; only when every one is on
    disk are they renamed into place. On failure the temporary files are removed, and so are
    the folders this call created.

    Parameters
    ----------
    out_dir : Path or str
        Created (with parents) if absent.
    files : Mapping[str, str or bytes]
        File name -> text (written as UTF-8) or bytes.

    Returns
    -------
    tuple[Path, ...]
        The written paths, in the order of ``files``.
    """
    out = Path(out_dir)
    with output_errors(out):
        return _write_files_atomically(out, files)


def _write_files_atomically(out: Path, files: Mapping[str, str | bytes]) -> tuple[Path, ...]:
    if out.exists() and not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    created: list[Path] = []
    probe = out
    while not probe.exists():
        created.append(probe)
        probe = probe.parent
    out.mkdir(parents=True, exist_ok=True)
    temps: dict[str, Path] = {}
    try:
        for name, text in files.items():
            temps[name] = _write_temp(out, name, text)
        for name, tmp in temps.items():
            os.replace(tmp, out / name)
    except BaseException:
        for tmp in temps.values():
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        for folder in created:  # deepest first; only empty folders go
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    fsync_dir(out)
    return tuple(out / name for name in files)


def write_synced(path: Path, text: str) -> None:
    """Write ``text`` to a new file ``path`` and fsync it (inside a folder built by
    :func:`building_folder`, which publishes the whole folder atomically)."""
    with open(path, "w", encoding="utf-8", newline="") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())


@contextlib.contextmanager
def building_folder(out: Path) -> Iterator[Path]:
    """Build a folder in a temporary sibling and publish it as ``out`` atomically.

    Yields the temporary folder (mode as a new folder gets under the umask). When the block
    succeeds, every sub-folder and the folder are fsynced and it replaces ``out`` (a
    previous ``out`` is moved aside first and removed after); when it fails, the temporary
    folder is removed and a previous ``out`` is put back.
    """
    with output_errors(out):
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    old: Path | None = None
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        for sub in tmp.iterdir():
            if sub.is_dir():
                fsync_dir(sub)
        fsync_dir(tmp)
        if out.exists():
            old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
            os.replace(out, old / out.name)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and (old / out.name).exists() and not out.exists():
            os.replace(old / out.name, out)  # put the previous folder back
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    fsync_dir(out.parent)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
