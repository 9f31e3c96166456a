"""Why an input path is not the file or folder a command needs: one phrase for the one-line
error (``F/nav.csv: is a folder, expected a file``), so a folder where a file is expected, a
file where a folder is, a broken or looping symlink and a missing path are told apart."""

from __future__ import annotations

from pathlib import Path


def _link_problem(path: Path) -> str | None:
    if path.is_symlink() and not path.exists():
        return "is a broken or looping symbolic link"
    return None


def file_problem(path: Path | str, missing: str = "no such file") -> str | None:
    """None when ``path`` is a readable file's path, else what it is instead (``missing``
    when there is nothing at all)."""
    path = Path(path)
    try:
        if path.is_file():
            return None
        link = _link_problem(path)
        if link is not None:
            return link
        if path.is_dir():
            return "is a folder, expected a file"
        return "is not a regular file" if path.exists() else missing
    except OSError as err:
        return f"cannot access: {err.strerror or err}"


def folder_problem(path: Path | str, missing: str = "no such folder") -> str | None:
    """None when ``path`` is a folder, else what it is instead (``missing`` when there is
    nothing at all)."""
    path = Path(path)
    try:
        if path.is_dir():
            return None
        link = _link_problem(path)
        if link is not None:
            return link
        return "is a file, expected a folder" if path.exists() else missing
    except OSError as err:
        return f"cannot access: {err.strerror or err}"


def exists_as_anything(path: Path | str) -> bool:
    """``path`` names something, a broken symlink included."""
    path = Path(path)
    return path.is_symlink() or path.exists()
