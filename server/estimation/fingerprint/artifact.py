"""Serialisation of trained models that cannot run code when loaded.

Blob: ``MAGIC | sha256(payload) | payload``; the payload is a NumPy ``.npz`` archive
read with ``allow_pickle=False``: one JSON document (``__doc__``) describing the model's
object tree, and the numeric arrays it refers to (``a0``, ``a1``, ...).

The JSON tree holds plain values (None, bool, int, float, str, lists, dicts) and tagged
nodes: arrays (``{"$a": i}``), tuples, dicts with non-string keys, scipy CSR matrices,
and objects — only of the classes in ``ALLOWED`` (this package's models and helpers, and
the few scikit-learn estimators the models use), rebuilt without calling their
constructors (``__new__`` + state). Any other class name is refused, so a tampered blob
can at most describe wrong numbers, never execute code.

The header of the document carries ``LIBRARY_VERSION``; a blob from another version is
refused with ArtifactError telling to retrain (there is no migration). Old pickled
artifacts (``LOCFP1``) are refused the same way, without being unpickled.
"""

from __future__ import annotations

import hashlib
import importlib
import io
import json
from typing import Any

import numpy as np

from .base import FingerprintModel

MAGIC = b"LOCFP2\n"
OLD_MAGICS = (b"LOCFP1\n",)
_DIGEST = 32
#: Bump whenever a model's fitted state changes shape; older artifacts are then refused.
LIBRARY_VERSION = "fingerprint-2.1"

#: Classes an artifact may instantiate (module, qualified name).
ALLOWED: frozenset[tuple[str, str]] = frozenset({
    ("server.estimation.fingerprint.knn", "KNNModel"),
    ("server.estimation.fingerprint.wknn", "WKNNModel"),
    ("server.estimation.fingerprint.nbc", "NBCModel"),
    ("server.estimation.fingerprint.tkbe", "TKBEModel"),
    ("server.estimation.fingerprint.kde", "KDEModel"),
    ("server.estimation.fingerprint.svm", "SVMModel"),
    ("server.estimation.fingerprint.propagation", "PropagationModel"),
    ("server.estimation.fingerprint.radiomap", "RadioMapModel"),
    ("server.estimation.fingerprint.dataset", "ReferencePoints"),
    ("server.estimation.fingerprint.calibration", "CovarianceCalibration"),
    ("server.estimation.fingerprint.features", "RssEncoder"),
    ("server.estimation.fingerprint.distance", "SquaredDistance"),
    ("server.estimation.fingerprint.gaussian", "GaussianRpStats"),
    ("server.estimation.fingerprint.base", "FloorKNN"),
    ("sklearn.svm._classes", "SVC"),
    ("sklearn.svm._classes", "SVR"),
    ("sklearn.ensemble._forest", "ExtraTreesClassifier"),
    ("sklearn.tree._classes", "ExtraTreeClassifier"),
})
_TREE = ("sklearn.tree._tree", "Tree")


class ArtifactError(ValueError):
    """The blob is not a valid, intact fingerprint-model artifact of this library version."""


# ---- encoding ----------------------------------------------------------------------------
class _Encoder:
    def __init__(self) -> None:
        self.arrays: list[np.ndarray] = []

    def array(self, a: np.ndarray) -> dict:
        if a.dtype == object:
            return {"$oa": [self.enc(v) for v in a.tolist()], "shape": list(a.shape)}
        if a.dtype.hasobject:
            raise ArtifactError(f"cannot store an array of dtype {a.dtype}")
        self.arrays.append(np.ascontiguousarray(a))
        return {"$a": len(self.arrays) - 1}

    def enc(self, o: Any) -> Any:
        if o is None or isinstance(o, (bool, str)):
            return o
        if isinstance(o, (int, np.integer)) and not isinstance(o, np.bool_):
            return int(o)
        if isinstance(o, np.bool_):
            return bool(o)
        if isinstance(o, (float, np.floating)):
            f = float(o)
            return f if np.isfinite(f) else {"$f": repr(f)}
        if isinstance(o, np.ndarray):
            return self.array(o)
        if isinstance(o, list):
            return [self.enc(v) for v in o]
        if isinstance(o, tuple):
            return {"$t": [self.enc(v) for v in o]}
        if isinstance(o, dict):
            if all(isinstance(k, str) for k in o) and not any(k.startswith("$") for k in o):
                return {k: self.enc(v) for k, v in o.items()}
            return {"$d": [[self.enc(k), self.enc(v)] for k, v in o.items()]}
        if isinstance(o, (set, frozenset)):
            return {"$t": [self.enc(v) for v in sorted(o, key=repr)]}
        from scipy import sparse

        if sparse.issparse(o):
            c = sparse.csr_matrix(o)
            return {"$csr": [self.array(c.data), self.array(c.indices), self.array(c.indptr)], "shape": list(c.shape)}
        cls = type(o)
        key = (cls.__module__, cls.__qualname__)
        if key == _TREE:
            args = o.__reduce__()[1]
            return {"$tree": self.enc(tuple(args)), "state": self.enc(o.__getstate__())}
        if key not in ALLOWED:
            raise ArtifactError(f"cannot store an object of class {key[0]}.{key[1]}")
        state = o.__getstate__()  # vars(o) unless the class says otherwise
        return {"$o": f"{key[0]}:{key[1]}", "state": self.enc(dict(state))}


def to_bytes(model: FingerprintModel) -> bytes:
    enc = _Encoder()
    doc = {"library_version": LIBRARY_VERSION, "model": enc.enc(model)}
    buf = io.BytesIO()
    arrays: dict[str, Any] = {f"a{i}": a for i, a in enumerate(enc.arrays)}
    arrays["__doc__"] = np.frombuffer(json.dumps(doc).encode(), dtype=np.uint8)
    np.savez(buf, allow_pickle=False, **arrays)
    payload = buf.getvalue()
    return MAGIC + hashlib.sha256(payload).digest() + payload


# ---- decoding ----------------------------------------------------------------------------
class _Decoder:
    def __init__(self, arrays) -> None:
        self.arrays = arrays

    def dec(self, o: Any) -> Any:
        if isinstance(o, list):
            return [self.dec(v) for v in o]
        if not isinstance(o, dict):
            return o
        if "$a" in o:
            return self.arrays[f"a{int(o['$a'])}"]
        if "$oa" in o:
            out = np.empty(len(o["$oa"]), dtype=object)
            out[:] = [self.dec(v) for v in o["$oa"]]
            return out.reshape(o["shape"])
        if "$f" in o:
            return float(o["$f"])
        if "$t" in o:
            return tuple(self.dec(v) for v in o["$t"])
        if "$d" in o:
            return {_hashable(self.dec(k)): self.dec(v) for k, v in o["$d"]}
        if "$csr" in o:
            from scipy import sparse

            data, indices, indptr = (self.dec(v) for v in o["$csr"])
            return sparse.csr_matrix((data, indices, indptr), shape=tuple(o["shape"]))
        if "$tree" in o:
            from sklearn.tree._tree import Tree

            tree = Tree(*self.dec(o["$tree"]))
            tree.__setstate__(self.dec(o["state"]))
            return tree
        if "$o" in o:
            module, _, name = str(o["$o"]).partition(":")
            if (module, name) not in ALLOWED:
                raise ArtifactError(f"artifact names a class that may not be loaded: {module}.{name}")
            cls = getattr(importlib.import_module(module), name)
            obj = cls.__new__(cls)
            state = self.dec(o["state"])
            if not isinstance(state, dict):
                raise ArtifactError("artifact object state is not a mapping")
            if hasattr(obj, "__setstate__"):
                obj.__setstate__(state)
            else:
                vars(obj).update(state)  # frozen dataclasses too: no __setattr__ involved
            return obj
        return {k: self.dec(v) for k, v in o.items()}


def _hashable(v):
    return tuple(_hashable(x) for x in v) if isinstance(v, (list, tuple)) else v


_OLD = "old pickled model artifact: refused (it could run code when loaded); retrain the model"


def checksum(blob: bytes) -> str:
    """Hex sha256 of the payload as recorded in the blob (for the server's records)."""
    blob = bytes(blob)
    if any(blob.startswith(m) for m in OLD_MAGICS):
        raise ArtifactError(_OLD)
    if not blob.startswith(MAGIC) or len(blob) < len(MAGIC) + _DIGEST:
        raise ArtifactError("not a fingerprint-model artifact")
    return blob[len(MAGIC): len(MAGIC) + _DIGEST].hex()


def from_bytes(blob: bytes) -> FingerprintModel:
    blob = bytes(blob)
    if any(blob.startswith(m) for m in OLD_MAGICS):
        raise ArtifactError(_OLD)
    if not blob.startswith(MAGIC) or len(blob) < len(MAGIC) + _DIGEST:
        raise ArtifactError("not a fingerprint-model artifact (bad header)")
    digest = blob[len(MAGIC): len(MAGIC) + _DIGEST]
    payload = blob[len(MAGIC) + _DIGEST:]
    if hashlib.sha256(payload).digest() != digest:
        raise ArtifactError("artifact checksum mismatch: corrupted or truncated")
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        doc = json.loads(arrays.pop("__doc__").tobytes().decode())
    except ArtifactError:
        raise
    except Exception as e:  # noqa: BLE001 - any malformed archive is one kind of error
        raise ArtifactError(f"unreadable artifact payload: {type(e).__name__}: {e}") from None
    version = doc.get("library_version") if isinstance(doc, dict) else None
    if version != LIBRARY_VERSION:
        raise ArtifactError(
            f"artifact made by fingerprint library version {version!r}, this server runs "
            f"{LIBRARY_VERSION!r}: retrain the model")
    try:
        model = _Decoder(arrays).dec(doc.get("model"))
    except ArtifactError:
        raise
    except Exception as e:  # noqa: BLE001
        raise ArtifactError(f"malformed artifact: {type(e).__name__}: {e}") from None
    if not isinstance(model, FingerprintModel):
        raise ArtifactError(f"artifact holds a {type(model).__name__}, not a fingerprint model")
    return model
