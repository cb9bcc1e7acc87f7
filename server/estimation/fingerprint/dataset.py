"""Training data for fingerprint models: `FingerprintSet` and its reference points.

A fingerprint is one RSS scan taken at a known position. Rows with the same
``(building, floor, label)`` — or, without a label, the same ``(building, floor, x, y)``
— are one *reference point* (RP), as API.md defines for surveys. ``building`` is an
optional extra (UJIIndoorLoc has it; API rows do not, so it defaults to 0).
"""

from __future__ import annotations

from array import array
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

KINDS = ("wifi", "ble")


def tx_kind(tx_id: str) -> str:
    """``"wifi"`` or ``"ble"`` from a transmitter id such as ``wifi:wap001``."""
    return tx_id.split(":", 1)[0]


#: rows `FingerprintSet.from_rows` writes into its matrix at once, and readings it checks at once
FILL_ROWS, FILL_READINGS = 4096, 1 << 16


def _float16_exact(dbm: np.ndarray) -> bool:
    """Whether every reading's float32 value is exactly a float16 (NaN equal to NaN)."""
    as32 = dbm.astype(np.float32)
    return bool(np.array_equal(as32.astype(np.float16).astype(np.float32), as32, equal_nan=True))


def _obj_array(values: Iterable | None, n: int) -> np.ndarray:
    out = np.empty(n, dtype=object)
    if values is not None:
        out[:] = list(values)
    return out


@dataclass(frozen=True)
class ReferencePoints:
    """The reference points of a `FingerprintSet`, one entry per RP."""

    keys: list[tuple]  # hashable identity, comparable across sets
    labels: list[str]  # display label (the survey label, or floor/x/y)
    x: np.ndarray
    y: np.ndarray
    floor: np.ndarray
    building: np.ndarray
    row_rp: np.ndarray  # for each fingerprint row, the index of its RP

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def xy(self) -> np.ndarray:
        return np.column_stack([self.x, self.y])


def rp_key(building: int, floor: int, label, x: float, y: float) -> tuple:
    if label is not None and label != "":
        return (int(building), int(floor), "L", str(label))
    return (int(building), int(floor), "P", round(float(x), 3), round(float(y), 3))


def rp_display_label(key: tuple) -> str:
    b, f, kind = key[0], key[1], key[2]
    if kind == "L":
        return key[3]
    prefix = f"b{b}:" if b else ""
    return f"{prefix}f{f}:{key[3]:.2f},{key[4]:.2f}"


@dataclass(init=False)
class FingerprintSet:
    """Fingerprints as numpy arrays (one row each).

    rss: (n, m) dBm, NaN = not heard (float64, or float32 when built so); tx_ids: the m transmitter ids (``wifi:...``,
    ``ble:...``); x, y: metres; floor: int; heading_deg: NaN when unknown;
    label: reference-point key (None when rows are grouped by position);
    building: int (0 unless the data set has buildings); user/device: optional
    groups for splitting; t: optional times.

    The constructor takes array-likes and fills ``heading_deg``, ``label`` and
    ``building`` when they are not given, so those three are always arrays.
    """

    rss: np.ndarray
    tx_ids: list[str]
    x: np.ndarray
    y: np.ndarray
    floor: np.ndarray
    heading_deg: np.ndarray
    label: np.ndarray
    building: np.ndarray
    user: np.ndarray | None
    device: np.ndarray | None
    t: np.ndarray | None
    meta: dict

    def __init__(
        self,
        rss: ArrayLike,
        tx_ids: Iterable[str],
        x: ArrayLike,
        y: ArrayLike,
        floor: ArrayLike,
        heading_deg: ArrayLike | None = None,
        label: Iterable | None = None,
        building: ArrayLike | None = None,
        user: Iterable | None = None,
        device: Iterable | None = None,
        t: ArrayLike | None = None,
        meta: dict | None = None,
    ) -> None:
        self.tx_ids = [str(tx) for tx in tx_ids]
        rss = np.asarray(rss)  # float32 / float16 are kept as they are (a large training set's memory), else float64
        if rss.dtype not in (np.float32, np.float16):
            rss = np.asarray(rss, dtype=float)
        self.rss = rss.reshape(len(rss) if rss.ndim == 2 else -1, len(self.tx_ids))  # (n, 0) too
        n = self.rss.shape[0]
        if len(set(self.tx_ids)) != len(self.tx_ids):
            raise ValueError("duplicate transmitter ids")
        self.x = np.asarray(x, dtype=float).reshape(n)
        self.y = np.asarray(y, dtype=float).reshape(n)
        self.floor = np.asarray(floor).astype(int).reshape(n)
        self.heading_deg = (
            np.full(n, np.nan) if heading_deg is None
            else np.asarray(heading_deg, dtype=float).reshape(n)
        )
        self.label = _obj_array(label, n)
        self.building = (
            np.zeros(n, dtype=int) if building is None
            else np.asarray(building).astype(int).reshape(n)
        )
        self.user = None if user is None else _obj_array(user, n)
        self.device = None if device is None else _obj_array(device, n)
        self.t = None if t is None else np.asarray(t, dtype=float).reshape(n)
        self.meta = {} if meta is None else meta

    # ---- construction -------------------------------------------------------------
    @classmethod
    def from_rows(
        cls, rows: Iterable[Mapping], tx_ids: Sequence[str] | None = None, dtype: type = float,
    ) -> FingerprintSet:
        """Build from row dicts as the server stores them:
        ``{x, y, floor, rss: {tx_id: dBm}, heading_deg?, label?, device?, user?, t?,
        building?}``. Transmitters are the sorted union of the rows' ids unless
        ``tx_ids`` is given (ids outside it are dropped).

        The rows are read once and never kept (an iterator streamed from the store is held
        one row at a time): each reading goes into flat arrays (12 bytes) and the matrix is
        filled at the end, a block of rows at a time. ``dtype``: float (default);
        ``np.float32`` halves the matrix; ``np.float16`` (the server's training) quarters it
        when every reading is exactly a float16 — whole dBm are — and is float32 otherwise,
        so the values are float32's."""
        fixed = tx_ids is not None
        col: dict[str, int] = {} if tx_ids is None else {tx: j for j, tx in enumerate(tx_ids)}
        heard, cols, values = array("i"), array("i"), array("d")  # readings per row; their columns, dBm
        xs, ys, headings, times = array("d"), array("d"), array("d"), array("d")
        floors, buildings = array("q"), array("q")
        labels: list = []
        users: list = []
        devices: list = []
        shared: dict = {}  # one object per distinct label / user / device
        given = dict.fromkeys(("building", "t", "user", "device"), False)
        for r in rows:
            k = 0
            for tx, v in r["rss"].items():
                j = col.get(tx)
                if j is None and not fixed:
                    j = col[tx] = len(col)
                if j is not None and v is not None:
                    cols.append(j)
                    values.append(float(v))
                    k += 1
            heard.append(k)
            xs.append(float(r["x"]))
            ys.append(float(r["y"]))
            floors.append(int(r["floor"]))
            h, b, t = r.get("heading_deg"), r.get("building"), r.get("t")
            headings.append(np.nan if h is None else float(h))
            buildings.append(0 if b is None else int(b))
            times.append(np.nan if t is None else float(t))
            label, user, device = r.get("label") or None, r.get("user"), r.get("device")
            labels.append(shared.setdefault(label, label))
            users.append(shared.setdefault(user, user))
            devices.append(shared.setdefault(device, device))
            for key, value in (("building", b), ("t", t), ("user", user), ("device", device)):
                given[key] = given[key] or value is not None
        names = list(tx_ids) if tx_ids is not None else sorted(col)
        renumber = np.arange(len(names))  # the columns were numbered as first heard: their sorted order
        if not fixed:
            renumber[[col[tx] for tx in names]] = np.arange(len(names))
        count = np.frombuffer(heard, dtype=np.int32)
        end = np.cumsum(count, dtype=np.int64)
        column, v = np.frombuffer(cols, dtype=np.int32), np.frombuffer(values, dtype=np.float64)
        target: np.dtype = np.dtype(dtype)
        if target == np.float16 and not all(_float16_exact(v[a: a + FILL_READINGS]) for a in range(0, len(v), FILL_READINGS)):
            target = np.dtype(np.float32)
        n = len(xs)
        rss: np.ndarray = np.full((n, len(names)), np.nan, dtype=target)
        for r0 in range(0, n, FILL_ROWS):  # in blocks: the temporaries stay small whatever n
            r1 = min(r0 + FILL_ROWS, n)
            a, b = int(end[r0] - count[r0]), int(end[r1 - 1])
            rss[np.repeat(np.arange(r0, r1), count[r0:r1]), renumber[column[a:b]]] = \
                v[a:b] if target == np.float64 else v[a:b].astype(np.float32)
        return cls(
            rss=rss,
            tx_ids=names,
            x=np.array(xs),
            y=np.array(ys),
            floor=np.array(floors),
            heading_deg=np.array(headings),
            label=labels,
            building=np.array(buildings) if given["building"] else None,
            user=users if given["user"] else None,
            device=devices if given["device"] else None,
            t=np.array(times) if given["t"] else None,
        )

    def to_rows(self) -> list[dict]:
        """Inverse of `from_rows` (RSS maps hold heard transmitters only)."""
        out = []
        for i in range(len(self)):
            heard = ~np.isnan(self.rss[i])
            row = {
                "x": float(self.x[i]), "y": float(self.y[i]), "floor": int(self.floor[i]),
                "rss": {self.tx_ids[j]: float(self.rss[i, j]) for j in np.flatnonzero(heard)},
            }
            if not np.isnan(self.heading_deg[i]):
                row["heading_deg"] = float(self.heading_deg[i])
            if self.label[i] is not None:
                row["label"] = self.label[i]
            if self.building[i]:
                row["building"] = int(self.building[i])
            if self.device is not None:
                row["device"] = self.device[i]
            if self.user is not None:
                row["user"] = self.user[i]
            out.append(row)
        return out

    # ---- selection ----------------------------------------------------------------
    def __len__(self) -> int:
        return self.rss.shape[0]

    def subset(self, rows) -> FingerprintSet:
        """Rows selected by an index array or boolean mask."""
        idx = np.asarray(rows)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        pick = lambda a: None if a is None else a[idx]  # noqa: E731
        n = len(self)
        meta = {k: v[idx] if isinstance(v, np.ndarray) and v.shape[:1] == (n,) else v for k, v in self.meta.items()}
        return replace(
            self, rss=self.rss[idx], x=self.x[idx], y=self.y[idx], floor=self.floor[idx],
            heading_deg=self.heading_deg[idx], label=self.label[idx],
            building=self.building[idx], user=pick(self.user), device=pick(self.device),
            t=pick(self.t), meta=meta,
        )

    def select_transmitters(self, tx_ids: Sequence[str]) -> FingerprintSet:
        """Columns reordered to ``tx_ids``; ids this set lacks become all-NaN columns (same dtype)."""
        return replace(self, rss=self.aligned_rss(tx_ids, self.rss.dtype), tx_ids=list(tx_ids), meta=dict(self.meta))

    def select_kinds(self, kinds: Sequence[str] | None) -> FingerprintSet:
        """Keep only transmitters whose id starts with one of ``kinds`` (e.g. ["ble"])."""
        if not kinds:
            return self
        kinds = tuple(kinds)
        bad = set(kinds) - set(KINDS)
        if bad:
            raise ValueError(f"unknown transmitter kinds {sorted(bad)}; use {KINDS}")
        keep = [t for t in self.tx_ids if tx_kind(t) in kinds]
        return self.select_transmitters(keep)

    def heard_mask(self) -> np.ndarray:
        return ~np.all(np.isnan(self.rss), axis=1)

    def drop_empty(self) -> FingerprintSet:
        """Rows that hear at least one transmitter."""
        m = self.heard_mask()
        return self if m.all() else self.subset(m)

    def aligned_rss(self, tx_ids: Sequence[str], dtype: type | np.dtype = float) -> np.ndarray:
        """The RSS matrix with columns in the order of ``tx_ids`` (NaN for unknown)."""
        col = {t: j for j, t in enumerate(self.tx_ids)}
        out = np.full((len(self), len(tx_ids)), np.nan, dtype=dtype)
        src = [(k, col[t]) for k, t in enumerate(tx_ids) if t in col]
        if src:
            dst, s = zip(*src, strict=True)
            out[:, list(dst)] = self.rss[:, list(s)]
        return out

    def scans(self) -> list[dict[str, float]]:
        """One ``{tx_id: dBm}`` dict per row (heard transmitters only)."""
        return [
            {self.tx_ids[j]: float(self.rss[i, j]) for j in np.flatnonzero(~np.isnan(self.rss[i]))}
            for i in range(len(self))
        ]

    # ---- reference points --------------------------------------------------------------
    def rp_keys(self) -> list[tuple]:
        return [
            rp_key(b, f, lab, x, y)
            for b, f, lab, x, y in zip(self.building, self.floor, self.label, self.x, self.y, strict=True)
        ]

    def reference_points(self) -> ReferencePoints:
        keys_per_row = self.rp_keys()
        index: dict[tuple, int] = {}
        row_rp = np.empty(len(self), dtype=int)
        for i, k in enumerate(keys_per_row):
            row_rp[i] = index.setdefault(k, len(index))
        keys = list(index)
        n_rp = len(keys)
        counts = np.bincount(row_rp, minlength=n_rp)
        x = np.bincount(row_rp, self.x, n_rp) / np.maximum(counts, 1)
        y = np.bincount(row_rp, self.y, n_rp) / np.maximum(counts, 1)
        return ReferencePoints(
            keys=keys,
            labels=[rp_display_label(k) for k in keys],
            x=x, y=y,
            floor=np.array([k[1] for k in keys], dtype=int),
            building=np.array([k[0] for k in keys], dtype=int),
            row_rp=row_rp,
        )


# ---- splitting ------------------------------------------------------------------------
def random_split(fs: FingerprintSet, test_fraction: float = 0.2, seed: int = 0):
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(fs))
    n_test = max(1, int(round(test_fraction * len(fs))))
    return fs.subset(np.sort(perm[n_test:])), fs.subset(np.sort(perm[:n_test]))


def group_split(fs: FingerprintSet, by: str, test_fraction: float = 0.2, seed: int = 0):
    """Hold out whole groups (``by`` = "user", "device", or a per-row array in ``meta``
    such as the UJI BLE beacon "power") until about ``test_fraction`` of the rows are
    held out. Returns (train, test, held_out_groups). ValueError when the set has no
    such column or a single group (nothing to hold out)."""
    groups = getattr(fs, by, None) if by in ("user", "device") else fs.meta.get(by)
    if groups is None:
        raise ValueError(f"this set has no {by!r} column to split by")
    names, inv, counts = np.unique(np.asarray(groups).astype(str), return_inverse=True, return_counts=True)
    if len(names) < 2:
        raise ValueError(f"cannot hold out by {by}: every row has the same {by} ({names[0] if len(names) else 'none'})")
    order = np.random.default_rng(seed).permutation(len(names))
    held, n_held = [], 0
    target = test_fraction * len(fs)
    for g in order:
        if n_held >= target:
            break
        if n_held + counts[g] > 1.6 * target and n_held > 0:
            continue  # skip a group that would overshoot badly
        held.append(g)
        n_held += counts[g]
    if len(held) == len(names):
        held = held[:-1]
    test_mask = np.isin(inv, held)
    return fs.subset(~test_mask), fs.subset(test_mask), sorted(names[held].tolist())
