"""The mutations of ``seqat bench fuzz``: seeded, replayable damage to a copy of a flight.

A case is fixed by ``(seed, index)``: :func:`case_rng` draws everything from
``numpy.random.default_rng([seed, index])``, so case ``K`` of seed ``S`` is the same whatever
the number of cases, and :func:`mutate` applied to the same base folder gives the same files.
Every mutation changes the folder (tests/pipeline/bench/test_bench_fuzz.py checks it); each
returns a one-line description of what it did.

Classes: byte flips and truncation (JPEG, LAS/LAZ, CSV, YAML), CSV field edits (text, NaN,
inf, huge values, empty fields), rows of the wrong width, deletions (files, folders, rows,
columns), duplications (rows, header, images), swapped columns (header only, values only,
both), encodings (BOM, CRLF, Latin-1, UTF-16, other separators), YAML edits, and path
oddities (spaces and unicode in folder names, symlinks, dangling and looping links, a file
where a folder is expected and the reverse, empty files, junk files beside the images, an
``--out`` that is a file or a non-empty folder of the user's).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

import numpy as np

T = TypeVar("T")

#: Field values a CSV edit writes (text, non-finite, huge, empty, odd number syntax).
BAD_VALUES = ("abc", "nan", "NaN", "inf", "-inf", "1e999", "-1e999", "1e300", "-1e300",
              "1e12", "-9e15", "", " ", "0x1F", '"1.5"', "1_000", "１２", "--1", "1e",
              "True", "null", "0", "-0", "1e-320", "123456789012345678901234567890")
#: Values a YAML edit writes in place of a scalar.
BAD_YAML_VALUES = ("nan", ".inf", "-.inf", "1e999", "-1", "0", "abc", "[]", "{}", "~", "''",
                   "[1, 2]", "1e12", "-1e12", "true", "!!binary aGVsbG8=", "&a x", "*a",
                   "'EPSG:4326'", "'EPSG:999999'", "0x10", "1_000")
#: Field separators a spreadsheet might write instead of commas.
OTHER_SEPARATORS = (";", "\t", "|")


@dataclasses.dataclass(frozen=True)
class Mutation:
    """What one case did to its folder: the class (``kind``), the file or folder it touched
    (relative to the case's input folder) and a one-line description."""

    kind: str
    target: str
    description: str


class NotApplicable(Exception):
    """The drawn mutation does not apply to this flight (drawn again)."""


@dataclasses.dataclass(frozen=True)
class CaseFolder:
    """The folders of one case: ``root/input`` holds the flight (``flight``, possibly renamed
    by a path mutation) and anything the mutation puts beside it; ``out`` is the ``--out`` of
    ``seqat run`` (beside the input, not in it)."""

    root: Path
    flight: Path
    out: Path

    @property
    def input(self) -> Path:
        return self.root / "input"


def case_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index)])


# --- the files of a flight -------------------------------------------------------------------

def _files(flight: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in flight.rglob("*") if p.is_file() and not p.is_symlink()
                  and p.suffix.lower() in suffixes)


def csv_files(flight: Path) -> list[Path]:
    return _files(flight, (".csv",))


def jpeg_files(flight: Path) -> list[Path]:
    return _files(flight, (".jpg", ".jpeg"))


def las_files(flight: Path) -> list[Path]:
    return _files(flight, (".las", ".laz"))


def yaml_files(flight: Path) -> list[Path]:
    return _files(flight, (".yaml", ".yml"))


def _pick(rng: np.random.Generator, items: Sequence[T]) -> T:
    if not items:
        raise NotApplicable
    return items[int(rng.integers(len(items)))]


def _rel(case: CaseFolder, path: Path) -> str:
    return path.relative_to(case.input).as_posix()


# --- CSV as text -------------------------------------------------------------------------------

def _read_lines(path: Path) -> list[str]:
    return path.read_bytes().decode("utf-8").splitlines()


def _write_lines(path: Path, lines: list[str]) -> None:
    path.write_bytes(("\n".join(lines) + "\n").encode("utf-8"))


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    lines = _read_lines(path)
    if len(lines) < 2:
        raise NotApplicable
    return lines[0].split(","), [line.split(",") for line in lines[1:]]


def _write_rows(path: Path, header: list[str], rows: list[list[str]]) -> None:
    _write_lines(path, [",".join(header)] + [",".join(r) for r in rows])


# --- byte-level mutations ------------------------------------------------------------------

def _any_file(case: CaseFolder, rng: np.random.Generator) -> Path:
    groups = [g for g in (csv_files(case.flight), jpeg_files(case.flight), las_files(case.flight),
                          yaml_files(case.flight)) if g]
    return _pick(rng, _pick(rng, groups))


def byte_flip(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _any_file(case, rng)
    data = bytearray(path.read_bytes())
    if not data:
        raise NotApplicable
    n = int(rng.integers(1, 33))
    # half the time in the first 4 KiB: headers, EXIF/XMP, the LAS header, the CSV header
    head = bool(rng.integers(2))
    span = min(len(data), 4096) if head else len(data)
    positions = sorted({int(p) for p in rng.integers(0, span, n)})
    for p in positions:
        data[p] ^= int(rng.integers(1, 256))
    path.write_bytes(bytes(data))
    where = "first 4 KiB" if head else "anywhere"
    return Mutation("byte_flip", _rel(case, path),
                    f"{len(positions)} byte(s) XOR-ed ({where}), first at offset {positions[0]}")


def truncate(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _any_file(case, rng)
    data = path.read_bytes()
    if len(data) < 2:
        raise NotApplicable
    size = int(rng.integers(1, len(data)))
    path.write_bytes(data[:size])
    return Mutation("truncate", _rel(case, path), f"cut to {size} of {len(data)} bytes")


def empty_file(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _any_file(case, rng)
    size = path.stat().st_size
    if size == 0:
        raise NotApplicable
    path.write_bytes(b"")
    return Mutation("empty_file", _rel(case, path), f"emptied ({size} bytes before)")


# --- CSV row and field edits -----------------------------------------------------------------

def csv_field(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    header, rows = _rows(path)
    r = int(rng.integers(len(rows)))
    c = int(rng.integers(len(rows[r])))
    value = str(_pick(rng, BAD_VALUES))
    if rows[r][c] == value:
        raise NotApplicable
    old = rows[r][c]
    rows[r][c] = value
    _write_rows(path, header, rows)
    name = header[c] if c < len(header) else f"#{c}"
    return Mutation("csv_field", _rel(case, path),
                    f"line {r + 2} field {name}: {old[:20]!r} -> {value!r}")


#: Finite values no real field has (huge, tiny, a decimal point lost), for numeric fields.
HUGE_VALUES = ("1e300", "-1e300", "1e20", "-1e12", "1e9", "5e-324", "1.7976931348623157e308")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def huge_value(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    """A numeric CSV field set to a finite value no real one has, or multiplied by 10^k."""
    path = _pick(rng, csv_files(case.flight))
    header, rows = _rows(path)
    cols = [c for c in range(len(header)) if all(c < len(r) and _is_number(r[c])
                                                  for r in rows[:5])]
    if not cols:
        raise NotApplicable
    r = int(rng.integers(len(rows)))
    c = int(_pick(rng, cols))
    old = rows[r][c]
    if rng.integers(3) == 0:
        value = repr(float(old) * 10.0 ** int(rng.integers(1, 8)))
    else:
        value = str(_pick(rng, HUGE_VALUES))
    if value == old:
        raise NotApplicable
    rows[r][c] = value
    _write_rows(path, header, rows)
    return Mutation("huge_value", _rel(case, path),
                    f"line {r + 2} field {header[c]}: {old[:20]!r} -> {value!r}")


def csv_row_width(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    header, rows = _rows(path)
    header_row = bool(rng.integers(4) == 0)
    target = header if header_row else rows[int(rng.integers(len(rows)))]
    line = 1 if header_row else rows.index(target) + 2
    if bool(rng.integers(2)) and len(target) > 1:
        target.pop(int(rng.integers(len(target))))
        what = "a field removed"
    else:
        target.insert(int(rng.integers(len(target) + 1)), str(_pick(rng, ("1.0", "", "x"))))
        what = "a field added"
    _write_rows(path, header, rows)
    return Mutation("csv_row_width", _rel(case, path), f"line {line}: {what}")


def csv_delete_rows(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    lines = _read_lines(path)
    if len(lines) < 2:
        raise NotApplicable
    mode = int(rng.integers(4))
    if mode == 0:
        drop = {0}
        what = "the header deleted"
    elif mode == 1:
        drop = set(range(1, len(lines)))
        what = "every data row deleted"
    else:
        k = int(rng.integers(1, max(2, len(lines) // 3)))
        drop = {int(i) for i in rng.choice(np.arange(1, len(lines)), size=min(k, len(lines) - 1),
                                           replace=False)}
        what = f"{len(drop)} row(s) deleted, first line {min(drop) + 1}"
    _write_lines(path, [x for i, x in enumerate(lines) if i not in drop])
    return Mutation("csv_delete_rows", _rel(case, path), what)


def csv_delete_column(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    header, rows = _rows(path)
    c = int(rng.integers(len(header)))
    name = header.pop(c)
    for row in rows:
        if c < len(row):
            row.pop(c)
    _write_rows(path, header, rows)
    return Mutation("csv_delete_column", _rel(case, path), f"column {name!r} deleted")


def csv_duplicate(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    lines = _read_lines(path)
    if len(lines) < 2:
        raise NotApplicable
    mode = int(rng.integers(3))
    if mode == 0:
        lines.insert(1 + int(rng.integers(len(lines) - 1)), lines[0])
        what = "the header repeated inside the file"
    else:
        i = int(rng.integers(1, len(lines)))
        at = i + 1 if mode == 1 else len(lines)
        lines.insert(at, lines[i])
        what = f"line {i + 1} duplicated {'after itself' if mode == 1 else 'at the end'}"
    _write_lines(path, lines)
    return Mutation("csv_duplicate", _rel(case, path), what)


def csv_swap_columns(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    header, rows = _rows(path)
    if len(header) < 2:
        raise NotApplicable
    a, b = (int(x) for x in rng.choice(len(header), size=2, replace=False))
    mode = str(_pick(rng, ("header", "values", "both")))
    targets = ([header] if mode != "values" else []) + (rows if mode != "header" else [])
    for row in targets:
        if max(a, b) < len(row):
            row[a], row[b] = row[b], row[a]
    if mode != "both" and all(r[a] == r[b] for r in rows if max(a, b) < len(r)) \
            and mode == "values":
        raise NotApplicable
    _write_rows(path, header, rows)
    return Mutation("csv_swap_columns", _rel(case, path),
                    f"columns {a + 1} and {b + 1} swapped ({mode})")


def csv_shuffle_rows(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    lines = _read_lines(path)
    if len(lines) < 4:
        raise NotApplicable
    i, j = (int(x) for x in rng.choice(np.arange(1, len(lines)), size=2, replace=False))
    if lines[i] == lines[j]:
        raise NotApplicable
    lines[i], lines[j] = lines[j], lines[i]
    _write_lines(path, lines)
    return Mutation("csv_shuffle_rows", _rel(case, path),
                    f"lines {min(i, j) + 1} and {max(i, j) + 1} swapped")


def csv_encoding(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, csv_files(case.flight))
    text = path.read_bytes().decode("utf-8")
    mode = str(_pick(rng, ("bom", "crlf", "latin1", "utf16", "separator", "spaces", "no_newline",
                           "nul")))
    if mode == "bom":
        data = b"\xef\xbb\xbf" + text.encode("utf-8")
    elif mode == "crlf":
        data = text.replace("\n", "\r\n").encode("utf-8")
    elif mode == "latin1":
        lines = text.splitlines()
        i = int(rng.integers(1, len(lines))) if len(lines) > 1 else 0
        lines[i] = lines[i].replace(",", ",\u00e9", 1)
        data = ("\n".join(lines) + "\n").encode("latin-1")
    elif mode == "utf16":
        data = text.encode("utf-16")
    elif mode == "separator":
        sep = str(_pick(rng, OTHER_SEPARATORS))
        data = text.replace(",", sep).encode("utf-8")
        mode = f"separator {sep!r}"
    elif mode == "spaces":
        data = text.replace(",", " , ").encode("utf-8")
    elif mode == "nul":
        data = text.encode("utf-8")
        at = int(rng.integers(len(data)))
        data = data[:at] + b"\x00" + data[at:]
    else:
        data = text.rstrip("\n").encode("utf-8")
    if data == path.read_bytes():
        raise NotApplicable
    path.write_bytes(data)
    return Mutation("csv_encoding", _rel(case, path), mode)


# --- targeted fields of binary files ----------------------------------------------------------

#: LAS header fields: name, byte offset, struct format (LAS 1.0-1.4 public header block).
LAS_FIELDS = (("header size", 94, "<H"), ("offset to point data", 96, "<I"),
              ("legacy point count", 107, "<I"), ("x scale", 131, "<d"),
              ("y scale", 139, "<d"), ("z scale", 147, "<d"), ("x offset", 155, "<d"),
              ("y offset", 163, "<d"), ("z offset", 171, "<d"), ("max x", 179, "<d"),
              ("min z", 211, "<d"))
#: Values written into a LAS header's float fields.
LAS_FLOATS = (0.0, float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 1e-300, 1e12,
              -1.0, 1000.0)


def las_header(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    import struct

    path = _pick(rng, las_files(case.flight))
    data = bytearray(path.read_bytes())
    name, offset, fmt = _pick(rng, LAS_FIELDS)
    size = struct.calcsize(fmt)
    if len(data) < offset + size:
        raise NotApplicable
    (old,) = struct.unpack_from(fmt, data, offset)
    if fmt == "<d":
        value: float = _pick(rng, LAS_FLOATS)
        if value == 1000.0:
            value = old * 1000.0
    else:
        value = int(_pick(rng, (0, 1, old + 1, max(old - 1, 0), old * 2 + 7,
                                2 ** (8 * size) - 1)))
    struct.pack_into(fmt, data, offset, value)
    if bytes(data) == path.read_bytes():
        raise NotApplicable
    path.write_bytes(bytes(data))
    return Mutation("las_header", _rel(case, path), f"{name}: {old!r} -> {value!r}")


#: Values written into an XMP number (padded to the length of the number they replace).
BAD_XMP_VALUES = ("nan", "inf", "-inf", "1e300", "-1e300", "1e12", "abc", "", "1e999",
                  "9999999")


def xmp_value(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    """Edit one number of a JPEG's XMP packet in place (same length, so the APP1 segment
    stays valid), or break the packet's XML."""
    import re

    path = _pick(rng, jpeg_files(case.flight))
    data = path.read_bytes()
    head = data[:262144]
    numbers = list(re.finditer(rb"<([A-Za-z-]+:[A-Za-z]+)>(-?[0-9.]+)</", head)) + \
        list(re.finditer(rb'([A-Za-z-]+:[A-Za-z]+)="(-?[0-9.]+)"', head))
    if not numbers:
        raise NotApplicable
    if rng.integers(5) == 0:
        m = _pick(rng, numbers)
        at = m.start() + 1 if head[m.start()] == ord("<") else m.start()
        new = data[:at] + b"?" + data[at + 1:]
        path.write_bytes(new)
        return Mutation("xmp_value", _rel(case, path),
                        f"XMP packet broken at {m.group(1).decode()}")
    m = _pick(rng, numbers)
    old = m.group(2)
    value = str(_pick(rng, BAD_XMP_VALUES)).encode()
    if len(value) > len(old):
        raise NotApplicable
    padded = value + b" " * (len(old) - len(value))
    path.write_bytes(data[:m.start(2)] + padded + data[m.end(2):])
    return Mutation("xmp_value", _rel(case, path),
                    f"XMP {m.group(1).decode()}: {old.decode()} -> {value.decode()!r}")


# --- YAML ------------------------------------------------------------------------------------

#: Values a YAML number is replaced with: huge, tiny, negative, zero.
YAML_NUMBERS = ("1e300", "-1e300", "1e12", "-1", "0", "1e-300", "-0.5", "1e6", "3.0e+20")


def yaml_number(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    """One number of a YAML file (a scalar or a list item) replaced by an implausible one."""
    import re

    path = _pick(rng, yaml_files(case.flight))
    lines = path.read_text(encoding="utf-8").splitlines()
    number = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?(?![\w.:])")
    spots = [(i, m) for i, x in enumerate(lines) if not x.lstrip().startswith("#")
             and ":" in x or x.lstrip().startswith("- ") for m in number.finditer(x)
             if not x[:m.start()].rstrip().endswith(("EPSG", "EPSG:"))]
    if not spots:
        raise NotApplicable
    i, m = _pick(rng, spots)
    value = str(_pick(rng, YAML_NUMBERS))
    if value == m.group(0):
        raise NotApplicable
    key = lines[i].split(":", 1)[0].strip()
    lines[i] = lines[i][:m.start()] + value + lines[i][m.end():]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Mutation("yaml_number", _rel(case, path),
                    f"line {i + 1} ({key}): {m.group(0)} -> {value}")


def yaml_edit(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    path = _pick(rng, yaml_files(case.flight))
    lines = path.read_text(encoding="utf-8").splitlines()
    keyed = [i for i, x in enumerate(lines) if ":" in x and not x.lstrip().startswith("#")]
    if not keyed:
        raise NotApplicable
    i = int(_pick(rng, keyed))
    mode = str(_pick(rng, ("value", "value", "value", "delete", "duplicate", "indent", "tab",
                           "unknown_key")))
    key = lines[i].split(":", 1)[0]
    if mode == "value":
        value = str(_pick(rng, BAD_YAML_VALUES))
        lines[i] = f"{key}: {value}"
        what = f"line {i + 1} {key.strip()}: -> {value}"
    elif mode == "delete":
        del lines[i]
        what = f"line {i + 1} ({key.strip()}) deleted"
    elif mode == "duplicate":
        lines.insert(i + 1, lines[i])
        what = f"line {i + 1} ({key.strip()}) duplicated"
    elif mode == "indent":
        lines[i] = "   " + lines[i]
        what = f"line {i + 1} ({key.strip()}) indented"
    elif mode == "tab":
        lines[i] = "\t" + lines[i]
        what = f"line {i + 1} ({key.strip()}) indented with a tab"
    else:
        lines.insert(i, key.replace(key.strip(), key.strip() + "x") + ": 1")
        what = f"unknown key {key.strip() + 'x'!r} before line {i + 1}"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Mutation("yaml_edit", _rel(case, path), what)


# --- deletions and duplications of files ---------------------------------------------------------

def delete_path(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    items = sorted(p for p in case.flight.rglob("*") if not p.name.startswith("."))
    path = _pick(rng, items)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()
    return Mutation("delete", _rel(case, path), "deleted")


def duplicate_image(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    images = jpeg_files(case.flight)
    path = _pick(rng, images)
    name = str(_pick(rng, ("{stem}_copy{suffix}", "copy of {stem}{suffix}", "zz_{stem}{suffix}",
                           "{stem}{suffix_upper}")))
    new = path.with_name(name.format(stem=path.stem, suffix=path.suffix,
                                     suffix_upper=".JPEG"))
    if new.exists():
        raise NotApplicable
    shutil.copy2(path, new)
    return Mutation("duplicate_image", _rel(case, new), f"a copy of {path.name}")


# --- path oddities ---------------------------------------------------------------------------

#: Folder names with spaces, unicode and shell-special characters.
ODD_NAMES = ("flight with spaces", "vol über Straße", "полёт", "航空写真", "a'b\"c", "x #1 $HOME",
             "-starts-with-dash", "tab\tname", "emoji 🛩")


def rename_flight(case: CaseFolder, rng: np.random.Generator) -> tuple[Mutation, CaseFolder]:
    name = str(_pick(rng, ODD_NAMES))
    new = case.flight.with_name(name)
    case.flight.rename(new)
    return (Mutation("odd_path", name, f"flight folder renamed to {name!r}"),
            dataclasses.replace(case, flight=new))


def odd_out(case: CaseFolder, rng: np.random.Generator) -> tuple[Mutation, CaseFolder]:
    mode = str(_pick(rng, ("name", "file", "nonempty", "symlink")))
    if mode == "name":
        name = str(_pick(rng, ODD_NAMES))
        out = case.out.with_name(name)
        return (Mutation("odd_out", name, f"--out named {name!r}"),
                dataclasses.replace(case, out=out))
    case.out.parent.mkdir(parents=True, exist_ok=True)
    if mode == "file":
        case.out.write_text("a file of the user's\n", encoding="utf-8")
        what = "--out is an existing file"
    elif mode == "nonempty":
        case.out.mkdir()
        (case.out / "eop.csv").write_text("the user's own eop.csv\n", encoding="utf-8")
        what = "--out is a non-empty folder of the user's (eop.csv)"
    else:
        target = case.root / "elsewhere"
        target.mkdir()
        case.out.symlink_to(target, target_is_directory=True)
        what = "--out is a symlink to an empty folder"
    return Mutation("odd_out", case.out.name, what), case


def symlinks(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    images = jpeg_files(case.flight)
    csvs = csv_files(case.flight)
    modes = ["dangling", "loop", "folder_link"] if images else []
    modes += ["csv_link", "csv_self"] if csvs else []
    if images:
        modes.append("image_link")
    mode = str(_pick(rng, modes))
    if mode in ("dangling", "loop"):
        folder = images[0].parent
        link = folder / ("missing.jpg" if mode == "dangling" else "loop.jpg")
        link.symlink_to("does_not_exist.jpg" if mode == "dangling" else link.name)
        return Mutation("symlink", _rel(case, link), f"a {mode} symlink among the images")
    if mode == "image_link":
        path = _pick(rng, images)
        path.unlink()
        other = images[(images.index(path) + 1) % len(images)]
        path.symlink_to(other.name)
        return Mutation("symlink", _rel(case, path),
                        f"replaced by a symlink to {other.name}")
    if mode == "folder_link":
        folder = images[0].parent
        moved = case.input / "moved images"
        shutil.move(str(folder), str(moved))
        folder.symlink_to(os.path.relpath(moved, folder.parent), target_is_directory=True)
        return Mutation("symlink", _rel(case, folder), "the images folder is a symlink")
    path = _pick(rng, csvs)
    if mode == "csv_self":
        path.unlink()
        path.symlink_to(path.name)
        return Mutation("symlink", _rel(case, path), "a symlink to itself")
    moved = case.input / "elsewhere" / path.name
    moved.parent.mkdir(exist_ok=True)
    shutil.move(str(path), str(moved))
    path.symlink_to(os.path.relpath(moved, path.parent))
    return Mutation("symlink", _rel(case, path), "a symlink to a file outside the flight")


def kind_swap(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    """A file where a folder is expected, or a folder where a file is."""
    folders = sorted(p for p in case.flight.rglob("*") if p.is_dir())
    files = sorted(p for p in case.flight.rglob("*") if p.is_file()
                   and p.suffix.lower() in (".csv", ".yaml", ".jpg", ".jpeg", ".laz", ".las"))
    if folders and (not files or bool(rng.integers(2))):
        path = _pick(rng, folders)
        shutil.rmtree(path)
        path.write_text("not a folder\n", encoding="utf-8")
        return Mutation("file_for_folder", _rel(case, path), "a file where a folder was")
    path = _pick(rng, files)
    path.unlink()
    path.mkdir()
    return Mutation("folder_for_file", _rel(case, path), "a folder where a file was")


def junk_files(case: CaseFolder, rng: np.random.Generator) -> Mutation:
    images = jpeg_files(case.flight)
    folder = images[0].parent if images else case.flight
    mode = str(_pick(rng, ("appledouble", "ds_store", "text_jpg", "hidden", "uppercase_tiny")))
    if mode == "appledouble" and images:
        path = folder / f"._{images[0].name}"
        path.write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        " + bytes(4000))
    elif mode == "ds_store":
        path = folder / ".DS_Store"
        path.write_bytes(b"\x00\x00\x00\x01Bud1" + bytes(2000))
    elif mode == "text_jpg":
        path = folder / "notes.jpg"
        path.write_text("this is not a picture\n", encoding="utf-8")
    elif mode == "hidden":
        path = folder / ".thumb.jpg"
        path.write_bytes(b"\xff\xd8\xff\xd9")
    else:
        path = folder / "TINY.JPEG"
        path.write_bytes(b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
                         b"\xff\xd9")
    return Mutation("junk_file", _rel(case, path), mode)


#: Every mutation with its draw weight. Path mutations that move the flight or its ``--out``
#: return a new :class:`CaseFolder`.
MUTATIONS: dict[str, tuple[float, Callable[..., object]]] = {
    "byte_flip": (3.0, byte_flip),
    "truncate": (2.0, truncate),
    "empty_file": (1.0, empty_file),
    "csv_field": (4.0, csv_field),
    "huge_value": (2.0, huge_value),
    "csv_row_width": (1.5, csv_row_width),
    "csv_delete_rows": (1.5, csv_delete_rows),
    "csv_delete_column": (1.0, csv_delete_column),
    "csv_duplicate": (1.0, csv_duplicate),
    "csv_swap_columns": (1.0, csv_swap_columns),
    "csv_shuffle_rows": (0.7, csv_shuffle_rows),
    "csv_encoding": (1.0, csv_encoding),
    "yaml_edit": (2.0, yaml_edit),
    "yaml_number": (1.5, yaml_number),
    "las_header": (1.0, las_header),
    "xmp_value": (1.0, xmp_value),
    "delete": (1.5, delete_path),
    "duplicate_image": (0.7, duplicate_image),
    "rename_flight": (0.5, rename_flight),
    "odd_out": (0.7, odd_out),
    "symlink": (1.0, symlinks),
    "kind_swap": (0.8, kind_swap),
    "junk_file": (0.5, junk_files),
}


def mutate(case: CaseFolder, rng: np.random.Generator,
           kinds: tuple[str, ...] | None = None) -> tuple[Mutation, CaseFolder]:
    """Draw one applicable mutation (weighted) and apply it to ``case``; the same rng state
    and folder give the same mutation. Draws again (at most 50 times) when the drawn one does
    not apply to this flight (no CSV, no YAML, ...); a failed draw leaves the folder as it was
    except for mutations that raise before writing, which all do."""
    names = [k for k in MUTATIONS if kinds is None or k in kinds]
    weights = np.array([MUTATIONS[k][0] for k in names])
    for _ in range(50):
        name = names[int(rng.choice(len(names), p=weights / weights.sum()))]
        try:
            result = MUTATIONS[name][1](case, rng)
        except NotApplicable:
            continue
        if isinstance(result, tuple):
            return result
        return result, case
    raise RuntimeError(f"no applicable mutation for {case.flight}")


def tree_digest(root: Path) -> dict[str, str]:
    """Digest of every entry under ``root`` (not following symlinks): file contents, link
    targets, folders; the key is the path relative to ``root``."""
    import hashlib

    out: dict[str, str] = {}
    if root.is_symlink() or not root.exists():
        return {".": f"link:{os.readlink(root)}" if root.is_symlink() else "absent"}
    if root.is_file():
        return {".": hashlib.sha256(root.read_bytes()).hexdigest()}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        base = Path(dirpath)
        for name in dirnames + filenames:
            p = base / name
            key = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[key] = f"link:{os.readlink(p)}"
            elif p.is_dir():
                out[key] = "dir"
            else:
                out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out
