"""Serialisation of trained models: ``MAGIC | sha256(payload) | payload``.

The payload is a pickle of our own trained model object. Unpickling runs code from
the blob, so this format is only acceptable because artifacts are produced and
stored by the server itself, never accepted from clients. The checksum is verified
before unpickling, so a truncated or corrupted blob is refused (ArtifactError)
rather than half-loaded.
"""

from __future__ import annotations

import hashlib
import pickle

from .base import FingerprintModel

MAGIC = b"LOCFP1\n"
_DIGEST = 32


class ArtifactError(ValueError):
    """The blob is not a valid, intact fingerprint-model artifact."""


def to_bytes(model: FingerprintModel) -> bytes:
    payload = pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)
    return MAGIC + hashlib.sha256(payload).digest() + payload


def checksum(blob: bytes) -> str:
    """Hex sha256 of the payload as recorded in the blob (for the server's records)."""
    if not blob.startswith(MAGIC) or len(blob) < len(MAGIC) + _DIGEST:
        raise ArtifactError("not a fingerprint-model artifact")
    return blob[len(MAGIC): len(MAGIC) + _DIGEST].hex()


def from_bytes(blob: bytes) -> FingerprintModel:
    blob = bytes(blob)
    if not blob.startswith(MAGIC) or len(blob) < len(MAGIC) + _DIGEST:
        raise ArtifactError("not a fingerprint-model artifact (bad header)")
    digest = blob[len(MAGIC): len(MAGIC) + _DIGEST]
    payload = blob[len(MAGIC) + _DIGEST:]
    if hashlib.sha256(payload).digest() != digest:
        raise ArtifactError("artifact checksum mismatch: corrupted or truncated")
    model = pickle.loads(payload)
    if not isinstance(model, FingerprintModel):
        raise ArtifactError(f"artifact holds a {type(model).__name__}, not a fingerprint model")
    return model
