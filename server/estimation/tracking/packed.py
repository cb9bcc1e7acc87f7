"""Arrays in stored tracker states as packed little-endian float32 (base64), not JSON lists.

A particle filter's state is thousands of numbers rewritten after every batch; as JSON
text each costs ≈ 20 bytes, packed 4 (5.3 in base64). float32 keeps 7 significant
digits: 0.02 mm at 200 m, far below any position error. ``unpack`` also reads the plain
lists of states stored before packing.
"""

from __future__ import annotations

import base64
from typing import Any

import numpy as np


def pack(a: np.ndarray) -> dict[str, Any]:
    a = np.ascontiguousarray(a, dtype="<f4")
    return {"f4": base64.b64encode(a.tobytes()).decode("ascii"), "shape": list(a.shape)}


def unpack(data: Any) -> np.ndarray:
    """A ``pack`` result, or a (nested) list of numbers, as a float64 array."""
    if isinstance(data, dict):
        raw = base64.b64decode(data["f4"], validate=True)
        return np.frombuffer(raw, dtype="<f4").astype(float).reshape(data["shape"])
    return np.asarray(data, dtype=float)
