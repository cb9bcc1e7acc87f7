"""File loaders: API survey CSV, UJIIndoorLoc CSV, UJI BLE library zone.

All paths are arguments; nothing here assumes where data sets live.
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np

from .dataset import FingerprintSet

SURVEY_COLUMNS = ("x", "y", "floor", "heading_deg", "label", "device", "t")
UJI_NOT_HEARD = 100.0


def read_survey_csv(source) -> FingerprintSet:
    """API.md's survey CSV: columns x, y, floor, heading_deg, label, device, t, then one
    column per transmitter id; an empty cell = not heard. ``source``: path or text."""
    text = source if isinstance(source, str) and "\n" in source else open(source, newline="").read()
    reader = csv.reader(io.StringIO(text))
    header = [h.strip() for h in next(reader)]
    missing = [c for c in ("x", "y", "floor") if c not in header]
    if missing:
        raise ValueError(f"survey CSV lacks columns {missing}")
    meta_cols = {c: header.index(c) for c in SURVEY_COLUMNS if c in header}
    tx_cols = [(j, h) for j, h in enumerate(header) if h not in SURVEY_COLUMNS]
    rows = list(reader)
    n = len(rows)
    rss = np.full((n, len(tx_cols)), np.nan)
    col = lambda name, conv, default: [  # noqa: E731
        conv(r[meta_cols[name]]) if name in meta_cols and r[meta_cols[name]].strip() else default for r in rows
    ]
    for i, r in enumerate(rows):
        for k, (j, _) in enumerate(tx_cols):
            if j < len(r) and r[j].strip():
                rss[i, k] = float(r[j])
    return FingerprintSet(
        rss=rss,
        tx_ids=[h for _, h in tx_cols],
        x=col("x", float, np.nan), y=col("y", float, np.nan), floor=col("floor", lambda s: int(float(s)), 0),
        heading_deg=col("heading_deg", float, np.nan),
        label=col("label", str.strip, None),
        device=col("device", str.strip, None) if "device" in meta_cols else None,
        t=col("t", float, np.nan) if "t" in meta_cols else None,
    )


def write_survey_csv(fs: FingerprintSet, path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(list(SURVEY_COLUMNS) + fs.tx_ids)
        for i in range(len(fs)):
            meta = [
                fs.x[i], fs.y[i], fs.floor[i],
                "" if np.isnan(fs.heading_deg[i]) else fs.heading_deg[i],
                fs.label[i] or "",
                "" if fs.device is None else fs.device[i],
                "" if fs.t is None or np.isnan(fs.t[i]) else fs.t[i],
            ]
            w.writerow(meta + ["" if np.isnan(v) else f"{v:g}" for v in fs.rss[i]])


def read_ujiindoorloc(path) -> FingerprintSet:
    """UJIIndoorLoc CSV (WAP001..WAP520, 100 = not heard, LONGITUDE/LATITUDE as metres,
    FLOOR, BUILDINGID, ..., USERID, PHONEID, TIMESTAMP). Rows that hear nothing are
    skipped; their count is in ``meta["skipped"]``. Reference points are grouped by
    (building, floor, x, y); user = USERID, device = PHONEID."""
    with open(path, newline="") as f:
        header = next(csv.reader(f))
    header = [h.strip().strip('"') for h in header]
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    wap = [j for j, h in enumerate(header) if h.upper().startswith("WAP")]
    col = {h.upper(): j for j, h in enumerate(header)}
    rss = data[:, wap]
    rss = np.where(rss == UJI_NOT_HEARD, np.nan, rss)
    keep = ~np.all(np.isnan(rss), axis=1)
    d = data[keep]
    fs = FingerprintSet(
        rss=rss[keep],
        tx_ids=["wifi:" + header[j].lower() for j in wap],
        x=d[:, col["LONGITUDE"]], y=d[:, col["LATITUDE"]],
        floor=d[:, col["FLOOR"]].astype(int),
        building=d[:, col["BUILDINGID"]].astype(int) if "BUILDINGID" in col else None,
        user=d[:, col["USERID"]].astype(int) if "USERID" in col else None,
        device=d[:, col["PHONEID"]].astype(int) if "PHONEID" in col else None,
        t=d[:, col["TIMESTAMP"]] if "TIMESTAMP" in col else None,
    )
    fs.meta["skipped"] = int((~keep).sum())
    return fs


def _read_matrix(path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", ndmin=2)


def read_uji_ble(directory) -> FingerprintSet:
    """UJI BLE RSS database, library zone: rss/lib_rss.csv (24 beacons, 100 = not
    heard), rss/lib_crd.csv (x, y metres), rss/lib_ids.csv (phone·10⁷ + power·10⁶ +
    campaign·10⁵ + point·100 + sample). Beacon columns are ``ble:lib<id>`` with ids from
    dep/lib.csv in order (23..46) when present. One floor (0). No label: point numbers
    are per campaign (point 1 of campaign 2 and of campaign 3 are different places), so
    reference points are grouped by position; device = phone; user = campaign. Rows
    that hear nothing are skipped."""
    rss = _read_matrix(os.path.join(directory, "rss", "lib_rss.csv"))
    crd = _read_matrix(os.path.join(directory, "rss", "lib_crd.csv"))
    ids = np.loadtxt(os.path.join(directory, "rss", "lib_ids.csv"), dtype=np.int64, ndmin=1)
    beacons = read_uji_ble_beacons(directory)
    names = [b["id"] for b in beacons] if len(beacons) == rss.shape[1] else [
        f"ble:lib{j + 1:02d}" for j in range(rss.shape[1])
    ]
    rss = np.where(rss == UJI_NOT_HEARD, np.nan, rss)
    keep = ~np.all(np.isnan(rss), axis=1)
    phone = ids // 10**7
    campaign = ids // 10**5 % 10
    fs = FingerprintSet(
        rss=rss[keep], tx_ids=names, x=crd[keep, 0], y=crd[keep, 1], floor=np.zeros(keep.sum(), int),
        user=campaign[keep], device=phone[keep],
    )
    fs.meta["skipped"] = int((~keep).sum())
    return fs


def read_uji_ble_beacons(directory) -> list[dict]:
    """dep/lib.csv → transmitter dicts ``{id, kind, floor, x, y}`` (API Transmitter)."""
    path = os.path.join(directory, "dep", "lib.csv")
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return [
            {"id": f"ble:lib{int(r['id']):02d}", "kind": "ble", "floor": 0, "x": float(r["x"]), "y": float(r["y"])}
            for r in csv.DictReader(f)
        ]


def load(path, fmt: str = "csv") -> FingerprintSet:
    if fmt == "csv":
        return read_survey_csv(path)
    if fmt == "ujiindoorloc":
        return read_ujiindoorloc(path)
    if fmt == "ujible":
        return read_uji_ble(path)
    raise ValueError(f"unknown format {fmt!r}")
