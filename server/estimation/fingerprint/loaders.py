"""File loaders: API survey CSV, UJIIndoorLoc CSV, UJI BLE library zone.

All paths are arguments; nothing here assumes where data sets live.
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np

from .dataset import FingerprintSet
from .ujiindoorloc import NOT_HEARD_DBM, device_name, parse_ujiindoorloc

SURVEY_COLUMNS = ("x", "y", "floor", "heading_deg", "label", "device", "t")


def read_survey_csv(source) -> FingerprintSet:
    """API.md's survey CSV: columns x, y, floor, heading_deg, label, device, t, then one
    column per transmitter id; an empty cell = not heard. ``source``: path or text."""
    if isinstance(source, str) and "\n" in source:
        text = source
    else:
        with open(source, newline="") as f:
            text = f.read()
    reader = csv.reader(io.StringIO(text))
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in ("x", "y", "floor") if c not in header]
    if missing:
        raise ValueError(f"survey CSV lacks columns {missing}")
    meta_cols = {c: header.index(c) for c in SURVEY_COLUMNS if c in header}
    tx_cols = [(j, h) for j, h in enumerate(header) if h not in SURVEY_COLUMNS]
    rows = list(reader)
    n = len(rows)
    rss = np.full((n, len(tx_cols)), np.nan)

    def col(name: str, conv, default) -> np.ndarray:
        j = meta_cols.get(name)
        return np.array([conv(r[j]) if j is not None and r[j].strip() else default for r in rows], dtype=object)

    for i, r in enumerate(rows):
        if len(r) != len(header):
            raise ValueError(f"survey CSV: data row {i} has {len(r)} cells, the header {len(header)}")
        for k, (j, name) in enumerate(tx_cols):
            if r[j].strip():
                try:
                    rss[i, k] = float(r[j])
                except ValueError:
                    raise ValueError(f"survey CSV: data row {i}, column {name}: not a number: {r[j]!r}") from None
    try:
        return FingerprintSet(
            rss=rss,
            tx_ids=[h for _, h in tx_cols],
            x=col("x", float, np.nan), y=col("y", float, np.nan), floor=col("floor", lambda s: int(float(s)), 0),
            heading_deg=col("heading_deg", float, np.nan),
            label=col("label", str.strip, None),
            device=col("device", str.strip, None) if "device" in meta_cols else None,
            t=col("t", float, np.nan) if "t" in meta_cols else None,
        )
    except ValueError as e:
        raise ValueError(f"survey CSV: a metadata cell (x, y, floor, heading_deg, t) is not a number: {e}") from None


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
    """UJIIndoorLoc CSV (parsed by ``ujiindoorloc``). Rows that hear nothing are skipped;
    their count is in ``meta["skipped"]``. Reference points are grouped by (building,
    floor, x, y); user = USERID, device = ``phone-<PHONEID>``."""
    with open(path, newline="", encoding="utf-8-sig") as f:
        survey = parse_ujiindoorloc(f)
    recs = survey.records
    col = {t: j for j, t in enumerate(survey.tx_ids)}
    rss = np.full((len(recs), len(col)), np.nan)
    for i, r in enumerate(recs):
        for t, v in r.rss.items():
            rss[i, col[t]] = v

    def column(values: list):
        return None if not values or any(v is None for v in values) else np.array(values)

    fs = FingerprintSet(
        rss=rss, tx_ids=survey.tx_ids,
        x=np.array([r.x for r in recs]), y=np.array([r.y for r in recs]), floor=np.array([r.floor for r in recs], int),
        building=column([r.building for r in recs]), user=column([r.user for r in recs]),
        device=column([r.device for r in recs]), t=column([r.timestamp for r in recs]),
    )
    fs.meta["skipped"] = survey.skipped
    return fs


def _read_matrix(path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", ndmin=2)


def read_uji_ble(directory) -> FingerprintSet:
    """UJI BLE RSS database, library zone: rss/lib_rss.csv (24 beacons, 100 = not
    heard), rss/lib_crd.csv (x, y metres), rss/lib_ids.csv (phone·10⁷ + power·10⁶ +
    campaign·10⁵ + point·100 + sample). Beacon columns are ``ble:lib<id>`` with ids from
    dep/lib.csv in order (23..46) when present. One floor (0). No label: point numbers
    are per campaign (point 1 of campaign 2 and of campaign 3 are different places), so
    reference points are grouped by position; device = ``phone-<phone>``; user = campaign. Rows
    that hear nothing are skipped."""
    rss = _read_matrix(os.path.join(directory, "rss", "lib_rss.csv"))
    crd = _read_matrix(os.path.join(directory, "rss", "lib_crd.csv"))
    ids = np.loadtxt(os.path.join(directory, "rss", "lib_ids.csv"), dtype=np.int64, ndmin=1)
    beacons = read_uji_ble_beacons(directory)
    names = [b["id"] for b in beacons] if len(beacons) == rss.shape[1] else [
        f"ble:lib{j + 1:02d}" for j in range(rss.shape[1])
    ]
    rss = np.where(rss == NOT_HEARD_DBM, np.nan, rss)
    keep = ~np.all(np.isnan(rss), axis=1)
    if rss.shape[0] != crd.shape[0] or rss.shape[0] != ids.shape[0]:
        raise ValueError(f"{directory}: lib_rss.csv has {rss.shape[0]} rows, lib_crd.csv {crd.shape[0]}, "
                         f"lib_ids.csv {ids.shape[0]}: they must match")
    phone = ids // 10**7
    power = ids // 10**6 % 10
    campaign = ids // 10**5 % 10
    fs = FingerprintSet(
        rss=rss[keep], tx_ids=names, x=crd[keep, 0], y=crd[keep, 1], floor=np.zeros(keep.sum(), int),
        user=campaign[keep], device=np.array([device_name(int(p)) for p in phone[keep]], dtype=object),
    )
    fs.meta["skipped"] = int((~keep).sum())
    fs.meta["power"] = power[keep]
    return fs


def read_uji_ble_beacons(directory) -> list[dict]:
    """dep/lib.csv → transmitter dicts ``{id, kind, floor, x, y}`` (API Transmitter);
    id ``ble:lib<id>``, a numeric id zero-padded to two digits."""
    path = os.path.join(directory, "dep", "lib.csv")
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return [
            {"id": _beacon_id(r["id"]), "kind": "ble", "floor": 0, "x": float(r["x"]), "y": float(r["y"])}
            for r in csv.DictReader(f)
        ]


def _beacon_id(raw: str) -> str:
    raw = raw.strip()
    return f"ble:lib{int(raw):02d}" if raw.isdigit() else f"ble:lib{raw.lower()}"


def read_json_rows(path) -> FingerprintSet:
    """The upload's JSON: a list of fingerprint rows ``{x, y, floor, rss, ...}`` or an
    object with a ``fingerprints`` list."""
    import json

    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    rows = doc.get("fingerprints") if isinstance(doc, dict) else doc
    if not isinstance(rows, list):
        raise ValueError(f"{path}: expected a list of fingerprints or {{\"fingerprints\": [...]}}")
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not {"x", "y", "floor", "rss"} <= set(r) or not isinstance(r["rss"], dict):
            raise ValueError(f"{path}: fingerprint {i} needs x, y, floor and an rss object")
    return FingerprintSet.from_rows(rows)


def read_msft_walks(directory, kinds: tuple[str, ...] = ("wifi", "ble")) -> FingerprintSet:
    """MSFT Indoor Location walks (a site floor directory with ``path_data_files/``):
    every WiFi / iBeacon scan placed at its waypoint-interpolated position; user = the
    walk's index (so ``--split user`` holds out whole walks). Parsed by the simulator's
    reader (client_sim.msft)."""
    from client_sim.msft import beacon_scans, read_walk, survey_rows, wifi_scans

    root = os.path.join(directory, "path_data_files") if os.path.isdir(os.path.join(directory, "path_data_files")) \
        else directory
    files = sorted(f for f in os.listdir(root) if f.endswith(".txt"))
    if not files:
        raise ValueError(f"{directory}: no walk files (*.txt) found")
    rows = []
    for w, name in enumerate(files):
        walk = read_walk(os.path.join(root, name))
        scans = (wifi_scans(walk) if "wifi" in kinds else []) + (beacon_scans(walk) if "ble" in kinds else [])
        for r in survey_rows(walk, scans):
            r["user"] = w
            rows.append(r)
    if not rows:
        raise ValueError(f"{directory}: the walks hold no scan with a known position")
    return FingerprintSet.from_rows(rows)


FORMATS = ("auto", "csv", "ujiindoorloc", "ujible", "json", "msft")


def detect_format(path) -> str:
    """The format of ``path`` from its shape: a directory with rss/lib_rss.csv = ujible,
    with path_data_files/ or walk .txt files = msft; *.json = json; a CSV whose header
    has WAPnnn and LONGITUDE = ujiindoorloc; any other file = csv."""
    path = os.fspath(path)
    if os.path.isdir(path):
        if os.path.exists(os.path.join(path, "rss", "lib_rss.csv")):
            return "ujible"
        if os.path.isdir(os.path.join(path, "path_data_files")) or any(f.endswith(".txt") for f in os.listdir(path)):
            return "msft"
        raise ValueError(f"{path}: a directory that is neither a UJI BLE database nor MSFT walks")
    if path.lower().endswith(".json"):
        return "json"
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        header = f.readline().upper()
    return "ujiindoorloc" if "WAP" in header and "LONGITUDE" in header else "csv"


def load(path, fmt: str = "csv") -> FingerprintSet:
    """Read a data set; ValueError (a clear message) for a missing path, the wrong kind of
    path for the format, or malformed contents."""
    if not os.path.exists(path):
        raise ValueError(f"{path}: no such file or directory")
    if fmt == "auto":
        fmt = detect_format(path)
    wants_dir = fmt in ("ujible", "msft")
    if wants_dir != os.path.isdir(path):
        raise ValueError(f"{path}: format {fmt} expects a {'directory' if wants_dir else 'file'}")
    if fmt == "csv":
        return read_survey_csv(path)
    if fmt == "ujiindoorloc":
        return read_ujiindoorloc(path)
    if fmt == "ujible":
        return read_uji_ble(path)
    if fmt == "json":
        return read_json_rows(path)
    if fmt == "msft":
        return read_msft_walks(path)
    raise ValueError(f"unknown format {fmt!r}; known: {', '.join(FORMATS)}")
