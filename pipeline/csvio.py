"""Strict, streaming CSV reading shared by the flight and result readers.

Every problem raises :class:`~seqat.errors.InputDataError` with ``path:line:`` and the field
and value, e.g. ``flight/nav.csv:4: field 'x_m': expected a finite number, got 'abc'``.

Rules (docs/formats.md): UTF-8, comma-separated, one header row naming every column once
(any order; no missing and no extra columns), blank lines ignored, spaces around values
ignored. Ids are non-empty and contain no whitespace, commas or quotes.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from seqat.errors import InputDataError

#: Allowed image, point and track ids: no whitespace, commas or quotes.
ID_PATTERN = re.compile(r"""^[^\s,"']+$""")


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
        """The finite number in ``field`` (``nan`` accepted only with ``allow_nan``)."""
        value = self.values[field]
        try:
            number = float(value)
        except ValueError:
            number = math.inf  # reported below
        if math.isfinite(number) or (allow_nan and math.isnan(number)):
            return number
        wanted = "a finite number or nan" if allow_nan else "a finite number"
        raise self.error(f"field {field!r}: expected {wanted}, got {value!r}")

    def integer(self, field: str) -> int:
        """The non-negative integer in ``field``."""
        value = self.values[field]
        if not value.isdigit():
            raise self.error(f"field {field!r}: expected a non-negative integer, got {value!r}")
        return int(value)


def read_csv(path: Path | str, columns: Sequence[str]) -> Iterator[CsvRow]:
    """Stream the data rows of a CSV file with exactly the given columns.

    Parameters
    ----------
    path : Path or str
    columns : sequence of str
        Required column names (header order is free; extra or repeated columns are errors).

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
        handle = open(path, encoding="utf-8", newline="")  # noqa: SIM115 - closed below
    except OSError as err:
        raise InputDataError(f"{where}: cannot read: {err.strerror or err}") from err
    with handle:
        reader = csv.reader(handle, skipinitialspace=True, strict=True)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputDataError(f"{where}:1: empty file, expected the header "
                                 f"{','.join(columns)}") from None
        except (csv.Error, UnicodeDecodeError) as err:
            raise InputDataError(f"{where}:{reader.line_num}: malformed CSV: {err}") from err
        if sorted(header) != sorted(columns):
            missing = [c for c in columns if c not in header]
            extra = [h for h in header if h not in columns or header.count(h) > 1]
            detail = "; ".join(part for part in (
                f"missing {', '.join(missing)}" if missing else "",
                f"unexpected {', '.join(dict.fromkeys(extra))}" if extra else "") if part)
            raise InputDataError(f"{where}:1: wrong columns ({detail}): expected "
                                 f"{','.join(columns)}, got {','.join(header)}")
        n_fields = len(header)
        while True:
            try:
                fields = next(reader)
            except StopIteration:
                return
            except (csv.Error, UnicodeDecodeError) as err:
                raise InputDataError(f"{where}:{reader.line_num}: malformed CSV: {err}") from err
            if not fields or (len(fields) == 1 and not fields[0].strip()):
                continue
            if len(fields) != n_fields:
                raise InputDataError(f"{where}:{reader.line_num}: expected {n_fields} fields "
                                     f"({','.join(header)}), got {len(fields)}")
            yield CsvRow(path=where, line=reader.line_num,
                         values={h: v.strip() for h, v in zip(header, fields, strict=True)})


def format_csv_line(values: Sequence[str]) -> str:
    """Join already formatted fields into one CSV line (ids never need quoting)."""
    return ",".join(values) + "\n"
