"""Survey bodies (JSON, CSV, UJIIndoorLoc CSV) parsed into validated fingerprints.

Every format ends in the same pydantic validation (`FingerprintIn`), so the edge rules
(RSS range, NaN, transmitter id format, empty scans) are written once; the valid rows
become domain ``FingerprintRecord``s. ``building`` (an optional CSV column; UJIIndoorLoc's
``BUILDINGID``) defaults to 0. Errors name the
field and the row: the 0-based index in ``fingerprints`` for JSON; for CSV the 0-based
data row under the header (blank and skipped rows count) plus the 1-based file ``line``.
"""

from __future__ import annotations

import csv
import io
import json
import re
from dataclasses import dataclass
from typing import Any

from pydantic import TypeAdapter, ValidationError

from server.domain import FingerprintRecord
from server.errors import Invalid, TooLarge, UnsupportedMedia
from server.estimation.fingerprint.ujiindoorloc import UjiFormatError, UjiRecord, parse_ujiindoorloc
from server.schemas import TX_ID_PATTERN, FingerprintIn

CSV_FIELDS = ("x", "y", "floor", "building", "heading_deg", "label", "device", "t")
MAX_REPORTED_ERRORS = 100
TX_ID_HELP = "wifi:<bssid>, wifi:<name>, ble:<uuid>:<major>:<minor> or ble:<name>, lower case"

_rows_adapter = TypeAdapter(list[FingerprintIn])


def invalid_rows(errors: list[dict[str, Any]], total: int | None = None) -> Invalid:
    """The body is not an acceptable survey: the first errors, each naming row and field."""
    total = len(errors) if total is None else total
    shown = errors[:MAX_REPORTED_ERRORS]
    if total > len(shown):
        shown.append(_error(None, "", f"... and {total - len(shown)} more error(s)"))
    return Invalid(shown)


@dataclass
class ParsedSurvey:
    fingerprints: list[FingerprintRecord]
    skipped: int = 0
    #: each fingerprint's 0-based data row in the body (JSON: its index in ``fingerprints``)
    rows: list[int] | None = None

    def row_of(self, index: int) -> int:
        return index if self.rows is None else self.rows[index]


def parse_survey(body: bytes, content_type: str, fmt: str | None, max_rows: int) -> ParsedSurvey:
    """Parse and validate a survey body; raises `Invalid` or `TooLarge`."""
    media = content_type.split(";")[0].strip().lower()
    fmt = fmt or {"text/csv": "csv", "application/csv": "csv", "application/json": "json", "": "json"}.get(media)
    skipped = 0
    if fmt == "ujiindoorloc":
        rows, positions, skipped = _uji_rows(_text(body))
    elif fmt == "csv":
        rows, positions = _csv_rows(_text(body))
    elif fmt == "json":
        rows, positions = _json_rows(body), None
    else:
        raise UnsupportedMedia(f"unsupported media type {media!r}: send application/json or text/csv")
    if len(rows) > max_rows:
        raise TooLarge(f"survey has {len(rows)} fingerprints; at most {max_rows} are accepted in one request")
    if not rows:
        raise invalid_rows([_error(None, "fingerprints", "the survey holds no fingerprints")])
    return ParsedSurvey(_validate(rows, positions), skipped, None if positions is None else [p[0] for p in positions])


def _text(body: bytes) -> str:
    try:
        return body.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise invalid_rows([_error(None, "body", f"not UTF-8 text: {exc}")]) from None


def _json_rows(body: bytes) -> list[Any]:
    try:
        doc = json.loads(body)
    except ValueError as exc:
        raise invalid_rows([_error(None, "body", f"malformed JSON: {exc}")]) from None
    except RecursionError:
        raise invalid_rows([_error(None, "body", "JSON nested too deeply")]) from None
    if not isinstance(doc, dict) or set(doc) != {"fingerprints"} or not isinstance(doc["fingerprints"], list):
        raise invalid_rows([_error(None, "body", 'expected an object {"fingerprints": [...]}')])
    return doc["fingerprints"]


class _CsvReader:
    """``csv.reader`` whose parse errors (a bare CR, a cell over 128 KiB, ...) are `Invalid`
    naming the data row and the file line."""

    def __init__(self, text: str):
        self._reader = csv.reader(io.StringIO(text, newline=""))
        self.data_row = -2  # the last row read: -1 is the header

    @property
    def line_num(self) -> int:
        return self._reader.line_num

    def __iter__(self) -> _CsvReader:
        return self

    def __next__(self) -> list[str]:
        try:
            cells = next(self._reader)
        except csv.Error as exc:
            row = None if self.data_row < -1 else self.data_row + 1
            where = "header" if row is None else "row"
            raise invalid_rows([_error(row, where, f"unreadable CSV: {exc}", line=self._reader.line_num)]) from None
        self.data_row += 1
        return cells


def _csv_rows(text: str) -> tuple[list[dict[str, Any]], list[tuple[int, int]]]:
    if "\r" in text.replace("\r\n", ""):
        lone = text.replace("\r\n", "\n\n").find("\r")  # same offsets, CRLF line ends hidden
        line = text.count("\n", 0, lone) + 1
        raise invalid_rows([_error(line - 2 if line > 1 else None, "row" if line > 1 else "header",
                                   "a carriage return outside a CRLF line end (CR-only line ends, or a CR in a "
                                   "cell): use LF or CRLF line ends", line=line)])
    reader = _CsvReader(text)
    header = [h.strip() for h in next(reader, [])]
    missing = [f for f in ("x", "y", "floor") if f not in header]
    if missing:
        raise invalid_rows([_error(None, "header", f"missing column(s) {', '.join(missing)}", line=1)])
    if len(set(header)) != len(header):
        raise invalid_rows([_error(None, "header", "duplicate column names", line=1)])
    fixed = [(i, h) for i, h in enumerate(header) if h in CSV_FIELDS]
    tx_columns = [(i, h) for i, h in enumerate(header) if h not in CSV_FIELDS]
    bad = [h for _, h in tx_columns if not re.match(TX_ID_PATTERN, h)]
    if bad:
        raise invalid_rows(
            [_error(None, f"header.{h}", f"column is neither a survey field nor a transmitter id ({TX_ID_HELP})", line=1)
             for h in bad]
        )
    rows, positions = [], []
    for data_row, cells in enumerate(reader):
        if not any(c.strip() for c in cells):
            continue
        _check_width(cells, header, data_row, reader.line_num)
        row: dict[str, Any] = {h: cells[i].strip() for i, h in fixed if cells[i].strip() != ""}
        row["rss"] = {h: cells[i].strip() for i, h in tx_columns if cells[i].strip() != ""}
        rows.append(row)
        positions.append((data_row, reader.line_num))
    return rows, positions


def _uji_rows(text: str) -> tuple[list[dict[str, Any]], list[tuple[int, int]], int]:
    """UJIIndoorLoc CSV through the shared parser, as rows for the common validation."""
    if text and not text.endswith("\n"):
        # the layout's files end each row with a line end: without one, the last cell may have been cut
        raise invalid_rows([_error(None, "body", "the file does not end with a line end: it may be truncated",
                                   line=text.count("\n") + 1)])
    try:
        survey = parse_ujiindoorloc(io.StringIO(text))
    except UjiFormatError as exc:
        raise invalid_rows([_error(exc.row, exc.field, str(exc), line=exc.line)]) from None
    except csv.Error as exc:
        raise invalid_rows([_error(None, "body", f"unreadable CSV: {exc}")]) from None
    rows = [_uji_row(r) for r in survey.records]
    return rows, [(r.row, r.line) for r in survey.records], survey.skipped


def _uji_row(record: UjiRecord) -> dict[str, Any]:
    row: dict[str, Any] = {"x": record.x, "y": record.y, "floor": record.floor, "rss": record.rss}
    if record.building is not None:  # BUILDINGID: a campus keeps its buildings apart
        row["building"] = record.building
    if record.device is not None:
        row["device"] = record.device
    if record.timestamp is not None:
        row["t"] = record.timestamp
    return row


def _check_width(cells: list[str], header: list[str], data_row: int, line: int) -> None:
    if len(cells) != len(header):
        raise invalid_rows([_error(data_row, "row", f"has {len(cells)} cells, header has {len(header)}", line=line)])


def _validate(rows: list[Any], positions: list[tuple[int, int]] | None) -> list[FingerprintRecord]:
    """Validate every row; ``positions`` maps a CSV row to its (data row, file line) for the report."""
    try:
        valid = _rows_adapter.validate_python(rows)
    except ValidationError as exc:
        errors = []
        for err in exc.errors(include_input=False, include_url=False):
            index, *field = err["loc"]
            msg = err["msg"]
            if field and field[-1] == "[key]":
                field = field[:-1]
                msg = f"unknown transmitter id format {field[-1]!r}; expected {TX_ID_HELP}"
            row, line = positions[int(index)] if positions else (int(index), None)
            errors.append(_error(row, ".".join(map(str, field)), msg, line=line))
        raise invalid_rows(errors, exc.error_count()) from None
    return [
        FingerprintRecord(f.x, f.y, f.floor, f.rss, heading_deg=f.heading_deg, t=f.t, device=f.device, label=f.label,
                          building=f.building)
        for f in valid
    ]


def _error(row: int | None, field: str, msg: str, line: int | None = None) -> dict[str, Any]:
    error: dict[str, Any] = {"row": row, "field": field, "msg": msg}
    if line is not None:
        error["line"] = line
    return error
