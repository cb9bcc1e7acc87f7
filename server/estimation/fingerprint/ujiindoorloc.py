"""The one parser of the UJIIndoorLoc CSV layout, for the survey upload and the evaluation CLI.

Columns: ``WAP001..WAP520`` (dBm, ``100`` = not heard), ``LONGITUDE``, ``LATITUDE``
(metres as given), ``FLOOR``, then optional ``BUILDINGID``, ``SPACEID``,
``RELATIVEPOSITION``, ``USERID``, ``PHONEID``, ``TIMESTAMP``. ``WAPnnn`` becomes the
transmitter id ``wifi:wapnnn`` and ``PHONEID`` the device ``phone-<PHONEID>``. Rows that
hear nothing are skipped and counted. Plain Python (no numpy), so the web layer can use it.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass
from functools import partial

NOT_HEARD_DBM = 100.0
REQUIRED = ("LONGITUDE", "LATITUDE", "FLOOR")


class UjiFormatError(ValueError):
    """The text is not UJIIndoorLoc CSV; ``row`` is the 0-based data row under the header
    (None for the header), ``line`` the 1-based file line, ``field`` the column."""

    def __init__(self, msg: str, field: str, row: int | None = None, line: int | None = None):
        super().__init__(msg)
        self.field, self.row, self.line = field, row, line


@dataclass(frozen=True, slots=True)
class UjiRecord:
    """One fingerprint row. ``row``/``line`` locate it in the file for error reports."""

    x: float
    y: float
    floor: int
    rss: dict[str, float]  # heard transmitters only: "wifi:wap001" -> dBm
    building: int | None = None
    user: int | None = None
    phone: int | None = None
    timestamp: int | None = None
    row: int = 0
    line: int = 0

    @property
    def device(self) -> str | None:
        return device_name(self.phone)


@dataclass
class UjiSurvey:
    tx_ids: list[str]  # every WAP column, in file order
    records: list[UjiRecord]
    skipped: int  # rows that heard nothing


def device_name(phone: int | None) -> str | None:
    """The device name of a UJI phone id (the same for every UJI data set)."""
    return None if phone is None else f"phone-{phone}"


def parse_ujiindoorloc(lines: Iterable[str]) -> UjiSurvey:
    """Parse UJIIndoorLoc CSV text (an open file or any iterable of lines); raises
    ``UjiFormatError`` at the first malformed header, row width or cell."""
    reader = csv.reader(lines)
    header = [h.strip().upper() for h in next(reader, [])]
    index = {h: i for i, h in enumerate(header)}
    missing = [f for f in REQUIRED if f not in index]
    if missing:
        raise UjiFormatError(f"missing UJIIndoorLoc column(s) {', '.join(missing)}", "header", line=1)
    waps = [(i, "wifi:" + h.lower()) for i, h in enumerate(header) if h.startswith("WAP")]
    optional = [index.get(f) for f in ("BUILDINGID", "USERID", "PHONEID", "TIMESTAMP")]
    records, skipped = [], 0
    for data_row, cells in enumerate(reader):
        if not cells:
            continue
        line = reader.line_num
        if len(cells) != len(header):
            raise UjiFormatError(f"has {len(cells)} cells, header has {len(header)}", "row", data_row, line)
        number = partial(_number, cells, header, data_row, line)
        rss = {tx: v for i, tx in waps if cells[i] != "100" and (v := number(i)) != NOT_HEARD_DBM}
        if not rss:
            skipped += 1
            continue
        building, user, phone, stamp = (None if i is None else number(i, int) for i in optional)
        records.append(UjiRecord(
            x=number(index["LONGITUDE"]), y=number(index["LATITUDE"]), floor=number(index["FLOOR"], int), rss=rss,
            building=building, user=user, phone=phone, timestamp=stamp, row=data_row, line=line,
        ))
    return UjiSurvey([tx for _, tx in waps], records, skipped)


def _number(cells: list[str], header: list[str], row: int, line: int, i: int, kind: type = float):
    """Cell ``i`` as ``kind`` (float or int), else ``UjiFormatError`` naming its column."""
    try:
        return kind(cells[i])
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise UjiFormatError(f"not {what}: {cells[i]!r}", header[i], row, line) from None
