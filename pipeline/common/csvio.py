"""Strict, streaming CSV reading shared by the flight and result readers.

Every problem raises :class:`~seqat.errors.InputDataError` with ``path:line:`` and the field
and value, e.g. ``flight/nav.csv:4: field 'x_m': expected a finite number, got 'abc'``.

Rules (docs/formats.md): UTF-8, comma-separated, one header row naming every column once
(any order; no missing and no extra columns), blank lines ignored, spaces around values
ignored. Ids are non-empty and contain no whitespace, commas or quotes.
"""

from __future__ import annotations

import codecs
import csv
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from seqat.errors import InputDataError

#: Allowed image, point and track ids: no whitespace, commas or quotes.
ID_PATTERN = re.compile(r"""^[^\s,"']+$""")
#: A number as spreadsheets and other CSV tools write it: ASCII decimal, optional exponent
#: (not Python's extras: ``1_000``, non-ASCII digits such as ``１２``, ``infinity``).
NUMBER_PATTERN = re.compile(r"^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$", re.ASCII)
#: ``nan`` as written by seqat, numpy, pandas and spreadsheets.
NAN_TEXT = frozenset({"nan", "NaN", "NAN", "-nan", "+nan"})


def magnitude_limit(field: str) -> tuple[float, str]:
    """The largest magnitude a value of column ``field`` can have, and what it is: no
    projected coordinate in metres exceeds 1e8 (the equator is 4e7 m long), no height
    1e5 m, no angle 1e4 degrees, no time 1e11 s (3000 years); latitudes and longitudes are
    bounded as such. A finite value beyond it is a corrupt field (a byte error, a missing
    decimal point), refused before it reaches the adjustment. Pixels have no bound here:
    the observations reader measures them against the image frame (one pixel far outside
    is left out with a warning, docs/formats.md)."""
    if field == "lat_deg":
        return 90.0, "latitude"
    if field == "lon_deg":
        return 360.0, "longitude"
    if field in ("z_m", "h_m"):
        return 1e5, "height"
    if field.endswith("_m"):
        return 1e8, "coordinate"
    if field.endswith("_deg"):
        return 1e4, "angle"
    if field.endswith("_s"):
        return 1e11, "time"
    return math.inf, "number"


@dataclass(frozen=True, kw_only=True)
class CsvRow:
    """One data row of a CSV file, addressed by column name."""

    path: str
    line: int
    values: dict[str, str]

    def error(self, message: str) -> InputDataError:
        """An :class:`InputDataError` located at this row."""
        return InputDataError(f"{self.path}:{self.line}: {message}")

    def ident(self, field: str) -> str:
        """The id in ``field`` (non-empty, no whitespace, commas or quotes)."""
        value = self.values[field]
        if not ID_PATTERN.match(value):
            raise self.error(f"field {field!r}: expected an id (non-empty, no spaces, commas "
                             f"or quotes), got {value!r}")
        return value

    def number(self, field: str, *, allow_nan: bool = False) -> float:
        """The finite number in ``field`` (``nan`` accepted only with ``allow_nan``), within
        :func:`magnitude_limit` of its column."""
        value = self.values[field]
        if allow_nan and value in NAN_TEXT:
            return math.nan
        number = float(value) if NUMBER_PATTERN.match(value) else math.inf
        if math.isfinite(number):
            limit, what = magnitude_limit(field)
            if abs(number) <= limit:
                return number
            raise self.error(f"field {field!r}: {value!r} is not a plausible {what} "
                             f"(magnitude above {limit:g})")
        wanted = "a finite number or nan" if allow_nan else "a finite number"
        raise self.error(f"field {field!r}: expected {wanted}, got {value!r}")

    def integer(self, field: str) -> int:
        """The non-negative integer in ``field``."""
        value = self.values[field]
        if not value.isdigit():
            raise self.error(f"field {field!r}: expected a non-negative integer, got {value!r}")
        return int(value)


def read_csv(path: Path | str, columns: Sequence[str],
             optional: Sequence[str] = ()) -> Iterator[CsvRow]:
    """Stream the data rows of a CSV file with exactly the given columns.

    Parameters
    ----------
    path : Path or str
    columns : sequence of str
        Required column names (header order is free; extra or repeated columns are errors).
    optional : sequence of str
        Columns the header may have (at most once each); a row's ``values`` lack a column
        the header does not have.

    Yields
    ------
    CsvRow
        One per non-blank data line, with its 1-based line number.

    Raises
    ------
    InputDataError
        Unreadable file, bad header, wrong number of fields, not UTF-8, malformed quoting.
    """
    where = str(path)
    try:
        handle = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as err:
        raise InputDataError(f"{where}: cannot read: {err.strerror or err}") from err
    with handle:
        reader = csv.reader(_decoded_lines(handle, where), skipinitialspace=True, strict=True)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputDataError(f"{where}:1: empty file, expected the header "
                                 f"{','.join(columns)}") from None
        except (csv.Error, UnicodeDecodeError) as err:
            raise InputDataError(f"{where}:{reader.line_num}: malformed CSV: {err}") from err
        check_header(where, header, columns, optional)
        while True:
            try:
                fields = next(reader)
            except StopIteration:
                return
            except (csv.Error, UnicodeDecodeError) as err:
                raise InputDataError(f"{where}:{reader.line_num}: malformed CSV: {err}") from err
            row = make_row(where, reader.line_num, header, fields)
            if row is not None:
                yield row


def decode_line(raw: bytes, where: str, line: int) -> str:
    """One line of a CSV file as text: UTF-8, a byte-order mark allowed on the first line.

    Raises
    ------
    InputDataError
        Not UTF-8: names the line, the column and the byte.
    """
    if line == 1 and raw.startswith(codecs.BOM_UTF8):
        raw = raw[len(codecs.BOM_UTF8):]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise InputDataError(f"{where}:{line}: not UTF-8: byte 0x{raw[err.start]:02x} at column "
                             f"{err.start + 1} (save the file as UTF-8)") from err


def _decoded_lines(handle: BinaryIO, where: str) -> Iterator[str]:
    for number, raw in enumerate(handle, start=1):
        yield decode_line(raw, where, number)


def check_header(where: str, header: Sequence[str], columns: Sequence[str],
                 optional: Sequence[str] = ()) -> None:
    """Raise unless ``header`` names every column of ``columns`` exactly once (and any of
    ``optional`` at most once)."""
    expected = [*columns, *(c for c in optional if c in header)]
    if sorted(header) != sorted(expected):
        missing = [c for c in columns if c not in header]
        extra = [h for h in header if h not in expected or header.count(h) > 1]
        detail = "; ".join(part for part in (
            f"missing {', '.join(missing)}" if missing else "",
            f"unexpected {', '.join(dict.fromkeys(extra))}" if extra else "") if part)
        raise InputDataError(f"{where}:1: wrong columns ({detail}): expected "
                             f"{','.join(columns)}, got {','.join(header)}")


def make_row(where: str, line: int, header: Sequence[str], fields: Sequence[str]) -> (
        CsvRow | None):
    """The row of one line's fields; None for a blank line."""
    if not fields or (len(fields) == 1 and not fields[0].strip()):
        return None
    if len(fields) != len(header):
        raise InputDataError(f"{where}:{line}: expected {len(header)} fields "
                             f"({','.join(header)}), got {len(fields)}")
    return CsvRow(path=where, line=line,
                  values={h: v.strip() for h, v in zip(header, fields, strict=True)})


class CsvTail:
    """The complete rows of a CSV file that another program is appending to (watch mode).

    Each :meth:`poll` returns the rows whose line has been completed (ends with a newline)
    since the last call; a partial last line is left for the next call. Same rules as
    :func:`read_csv` (``optional`` columns as there), one line per row (no quoted newlines).
    The file may not exist yet.

    Raises (from :meth:`poll`)
    ------
    InputDataError
        Bad header or row, not UTF-8, or the file shrank (rewritten instead of appended to).
    """

    def __init__(self, path: Path | str, columns: Sequence[str],
                 optional: Sequence[str] = ()) -> None:
        self.path = Path(path)
        self.columns = tuple(columns)
        self.optional = tuple(optional)
        self._offset = 0
        self._line = 0
        self._header: list[str] | None = None

    def poll(self) -> list[CsvRow]:
        where = str(self.path)
        try:
            with self.path.open("rb") as handle:
                handle.seek(0, 2)
                size = handle.tell()
                if size < self._offset:
                    raise InputDataError(f"{where}: the file shrank from {self._offset} to "
                                         f"{size} bytes; a watched file may only be appended to")
                handle.seek(self._offset)
                data = handle.read(size - self._offset)
        except FileNotFoundError:
            return []
        except OSError as err:
            raise InputDataError(f"{where}: cannot read: {err.strerror or err}") from err
        end = data.rfind(b"\n") + 1
        self._offset += end
        rows: list[CsvRow] = []
        for raw in data[:end].splitlines():
            self._line += 1
            text = decode_line(raw, where, self._line)
            try:
                fields = next(csv.reader([text], skipinitialspace=True, strict=True), [])
            except csv.Error as err:
                raise InputDataError(f"{where}:{self._line}: malformed CSV: {err}") from err
            if self._header is None:
                self._header = [h.strip() for h in fields]
                check_header(where, self._header, self.columns, self.optional)
                continue
            row = make_row(where, self._line, self._header, fields)
            if row is not None:
                rows.append(row)
        return rows


def format_csv_line(values: Sequence[str]) -> str:
    """Join already formatted fields into one CSV line (ids never need quoting)."""
    return ",".join(values) + "\n"
