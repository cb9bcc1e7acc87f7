"""Arrays in stored tracker states as packed bytes (deflated, base85 text), not JSON lists.

A particle filter's state is thousands of numbers rewritten after every batch; as JSON
text each costs ≈ 20 bytes. Particles and weights are stored as one byte per number:

* **Particles** on a grid per column: value = lo + k·step, k an unsigned byte (0–255),
  lo the column's smallest value and step its range / 255 when the grid was drawn
  (``fit_grid``). The resolution follows the cloud: its spread over 255, i.e. step/√12 ≈
  0.8 % of a Gaussian cloud's standard deviation (a cloud of σ = 2 m: 1.5 cm; a heading
  bias of σ = 2°: 0.016°; a step scale of σ = 0.02: 0.00015), far below what a step adds
  to each column (position ≈ 0.2 m, bias 1°, scale 0.003: ``selfcal``).
* **Weights** as their ratio to the largest, rounded on a log scale: 2^(−k/16), k a byte
  (0–254, 16 codes per halving: the ratio within ±2.2 % of the exact one, down to 1.5·10⁻⁵ of
  the largest); k = 255 is 0 (a weight below that carries nothing in 1,000 particles).
  The ratios are exact float64 constants (``_RATIO``, computed in decimal arithmetic so
  every machine has the same table), and the weights held are ratio / sum of ratios.

The filter holds exactly those values (``snap``, ``weights_as_stored``), so storing them
loses nothing and a restored filter continues exactly as the one that was stored. The
codes are deflated (zlib without its header: ≈ 10 % less for particles, whose codes crowd
the middle of their grid; ≈ 17 % for weights) and written as base85 (RFC 1924, as
``base64.b85encode`` but vectorised: 5 characters per 4 bytes, none of them a quote or a
backslash, so JSON keeps them as they are): 1,000 particles of 4 columns, ≈ 4,500
characters; their weights, ≈ 1,050 (none when uniform). As float16 offsets and float32
weights in base64 they took 10,700 and 5,300.

``unpack`` also reads the older forms: float32 packs (``{"f4": base64, "shape"}``), float16
offsets from an anchor (``{"f2": base64, "shape", "anchor"}``) and the plain lists stored
before packing; ``unpack_weights`` float32 packs, lists and None (uniform).
"""

from __future__ import annotations

import base64
import zlib
from decimal import Decimal, localcontext
from typing import Any

import numpy as np

#: largest code of a grid column (codes 0..LEVELS, one byte)
LEVELS = 255
#: weight codes per halving of the ratio to the largest weight
PER_OCTAVE = 16
#: the weight code that stands for 0
ZERO_WEIGHT = 255


def _ratios() -> np.ndarray:
    """2^(−k/16) for k = 0..254 and 0 for k = 255, each the float64 nearest the exact value."""
    with localcontext() as ctx:
        ctx.prec = 40
        frac = [float(Decimal(2) ** (Decimal(-j) / PER_OCTAVE)) for j in range(PER_OCTAVE)]
    k = np.arange(ZERO_WEIGHT)
    return np.append(np.ldexp(np.asarray(frac)[k % PER_OCTAVE], -(k // PER_OCTAVE)), 0.0)


_RATIO = _ratios()


#: base85's digits (RFC 1924, as ``base64.b85encode``)
_B85 = np.frombuffer(b"0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz!#$%&()*+-;<=>?@^_`{|}~",
                     dtype=np.uint8)
_B85_VALUE = np.full(256, 255, dtype=np.uint8)
_B85_VALUE[_B85] = np.arange(85)
_B85_POW = 85.0 ** np.arange(4, -1, -1)


def b85encode(raw: bytes) -> str:
    """``base64.b85encode(raw).decode()``, vectorised (the standard library's loops in Python
    take ≈ 0.3 ms to write a state's 5 kB, 0.6 ms to read it)."""
    pad = -len(raw) % 4
    words = np.frombuffer(raw + b"\0" * pad, dtype=">u4").astype(float)
    digits = np.empty((len(words), 5), dtype=np.uint8)
    for i in range(4, -1, -1):  # float64 holds every 32-bit word, and floor(w / 85) is exact for them
        q = np.floor(words / 85)
        digits[:, i] = words - 85 * q
        words = q
    return _B85[digits].tobytes()[: 5 * len(digits) - pad].decode("ascii")


def b85decode(text: str) -> bytes:
    """``base64.b85decode(text)``, vectorised; ValueError for a character or group that is not base85."""
    data = text.encode("ascii")  # UnicodeEncodeError is a ValueError
    pad = -len(data) % 5
    values = _B85_VALUE[np.frombuffer(data + b"~" * pad, dtype=np.uint8)]
    if np.any(values == 255):
        raise ValueError("not base85 text")
    words = values.reshape(-1, 5).astype(float) @ _B85_POW  # exact: at most 85⁵ − 1 < 2⁵³
    if np.any(words > 0xFFFFFFFF):
        raise ValueError("base85 overflow in a group")
    return words.astype(">u4").tobytes()[: 4 * len(words) - pad]


def _text(codes: np.ndarray) -> str:
    """Bytes as raw deflate (zlib, no header), written as base85."""
    z = zlib.compressobj(9, zlib.DEFLATED, -15)
    return b85encode(z.compress(codes.tobytes()) + z.flush())


def _codes_from_text(text: str, count: int) -> np.ndarray:
    """``count`` bytes from ``_text`` (ValueError when the text holds other than that)."""
    z = zlib.decompressobj(-15)
    try:
        raw = z.decompress(b85decode(text), count + 1)
    except zlib.error as e:
        raise ValueError(f"stored codes do not inflate: {e}") from None
    if len(raw) != count or not z.eof:
        raise ValueError(f"stored codes are not {count} bytes")
    return np.frombuffer(raw, dtype=np.uint8)


# -- particles: a byte per value on a grid per column ---------------------------------------
def fit_grid(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid (lo, step) per column of the rows ``a``: lo its smallest value, step its range / 255."""
    lo = a.min(axis=0)
    return lo, (a.max(axis=0) - lo) / LEVELS


def _codes(a: np.ndarray, lo: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Each value's grid index rint((a − lo)/step) as floats (0 in a column without spread), not
    yet clipped to the grid; computed in place on one array of ``a``'s layout (a hot path)."""
    k = np.subtract(a, lo, order="K")
    np.divide(k, np.where(step > 0, step, 1.0), out=k)
    np.rint(k, out=k)
    if not np.all(step > 0):
        k[..., step <= 0] = 0.0
    return k


def _values(codes: np.ndarray, lo: np.ndarray, step: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """k·step + lo (float64): the one expression both rounding and loading use (into ``out``,
    which may be ``codes`` itself, when given)."""
    v = np.multiply(codes, step, out=out, dtype=float)
    v += lo
    return v


def snap(a: np.ndarray, lo: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Rows of ``a`` on the grid (values outside it are taken to its ends)."""
    k = _codes(a, lo, step)
    return _values(np.clip(k, 0, LEVELS, out=k), lo, step, out=k)


def on_grid(a: np.ndarray, lo: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Per column: every value of ``a`` is a grid value already (then snapping changes nothing)."""
    k = _codes(a, lo, step)
    inside = (k >= 0) & (k <= LEVELS)
    return np.all(inside & (_values(np.clip(k, 0, LEVELS), lo, step) == a), axis=0)


def pack_grid(a: np.ndarray, lo: np.ndarray, step: np.ndarray) -> dict[str, Any]:
    """Rows of ``a`` (grid values: ``snap``) as their codes."""
    codes = np.clip(_codes(a, lo, step), 0, LEVELS).astype(np.uint8)
    return {"u8": _text(codes), "shape": list(a.shape),
            "lo": np.asarray(lo, float).tolist(), "step": np.asarray(step, float).tolist()}


def grid_of(data: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """The grid of a ``pack_grid`` result (None for the older forms)."""
    if isinstance(data, dict) and "u8" in data:
        return np.asarray(data["lo"], float), np.asarray(data["step"], float)
    return None


# -- float32 (values that no grid holds: non-finite ones) ------------------------------------
def pack(a: np.ndarray) -> dict[str, Any]:
    a = np.ascontiguousarray(a, dtype="<f4")
    return {"f4": base64.b64encode(a.tobytes()).decode("ascii"), "shape": list(a.shape)}


def unpack(data: Any) -> np.ndarray:
    """A ``pack_grid`` or ``pack`` result, an older float16-offset pack, or a (nested) list of
    numbers, as a float64 array."""
    if isinstance(data, dict):
        if "u8" in data:
            shape = [int(k) for k in data["shape"]]
            codes = _codes_from_text(data["u8"], int(np.prod(shape))).reshape(shape)
            lo, step = grid_of(data)  # type: ignore[misc]
            return _values(codes, lo, step)
        if "f2" in data:  # before the grid: float16 offsets from an anchor
            raw = base64.b64decode(data["f2"], validate=True)
            offsets = np.frombuffer(raw, dtype="<f2").astype(float).reshape(data["shape"])
            return np.asarray(data["anchor"], float) + offsets
        raw = base64.b64decode(data["f4"], validate=True)
        return np.frombuffer(raw, dtype="<f4").astype(float).reshape(data["shape"])
    return np.asarray(data, dtype=float)


# -- weights: a byte each, on a log scale ----------------------------------------------------
def _weight_codes(w: np.ndarray) -> np.ndarray:
    top = np.max(w)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.rint(-PER_OCTAVE * np.log2(w / top))
    return np.where((w > 0) & (k < ZERO_WEIGHT), k, ZERO_WEIGHT).astype(np.uint8)


def _weights(codes: np.ndarray) -> np.ndarray:
    r = _RATIO[codes]
    return r / r.sum()


def weights_as_stored(w: np.ndarray) -> np.ndarray:
    """The weights ``pack_weights`` keeps (summing to 1); ``w`` needs a positive largest value.
    Applied to its own result it changes nothing."""
    return _weights(_weight_codes(w))


def pack_weights(w: np.ndarray) -> dict[str, Any] | None:
    """Weights (values of ``weights_as_stored``) as their codes; None when all are equal."""
    codes = _weight_codes(w)
    if np.all(codes == codes[0]):
        return None
    return {"log2": _text(codes), "per_octave": PER_OCTAVE}


def unpack_weights(data: Any, n: int) -> np.ndarray:
    """``n`` weights from ``pack_weights``, an older float32 pack or list (float64, as stored),
    or None (uniform)."""
    if data is None:
        return np.full(n, 1.0 / n)
    if isinstance(data, dict) and "log2" in data:
        if data.get("per_octave") != PER_OCTAVE:
            raise ValueError(f"unsupported weight scale {data.get('per_octave')!r}")
        codes = _codes_from_text(data["log2"], n)
        if np.all(codes == ZERO_WEIGHT):
            raise ValueError("stored weights are all 0")
        return _weights(codes)
    return unpack(data).reshape(n)
