"""Fingerprint models: pure Python (numpy/scipy/scikit-learn), no web or DB imports.

    from server.estimation.fingerprint import FingerprintSet, make_model, to_bytes, from_bytes

    fs = FingerprintSet.from_rows(rows)                   # rows as stored by the server
    model = make_model("wknn", {}, use_heading=False, kinds=["wifi"]).fit(fs)  # or "knn", ...
    fix = model.locate({"wifi:wap001": -70.0}, heading_deg=None)   # -> types.Fix
    blob = to_bytes(model); model = from_bytes(blob)     # sha256-checked npz + JSON, no pickle
"""

from .artifact import ArtifactError, checksum, from_bytes, to_bytes
from .base import FingerprintModel, NotFittedError, UnknownTransmittersError
from .dataset import FingerprintSet, ReferencePoints, group_split, random_split
from .features import RssEncoder, heading_features
from .fusion import cold_start_fix, exp_weights, fuse_fixes
from .kde import KDEModel
from .knn import KNNModel
from .metrics import Metrics, evaluate, fit_and_validate, held_out_stage, holdout_split
from .nbc import NBCModel
from .posterior import Prediction
from .propagation import PropagationModel
from .registry import ALGORITHMS, make_model
from .svm import SVMModel
from .tkbe import TKBEModel
from .wknn import WKNNModel

__all__ = [
    "ALGORITHMS", "ArtifactError", "FingerprintModel", "FingerprintSet", "KDEModel", "KNNModel", "Metrics",
    "NBCModel", "NotFittedError", "Prediction", "PropagationModel", "ReferencePoints", "RssEncoder",
    "SVMModel", "TKBEModel", "UnknownTransmittersError", "WKNNModel", "checksum", "cold_start_fix", "evaluate",
    "exp_weights", "fit_and_validate", "from_bytes", "fuse_fixes", "group_split",
    "heading_features", "held_out_stage", "holdout_split", "make_model", "random_split", "to_bytes",
]
