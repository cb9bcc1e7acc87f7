"""Where the shared data sets are by default: ``../shared/data`` beside the repository,
whatever the working directory a benchmark is started from."""

from __future__ import annotations

from pathlib import Path

SHARED_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
UJIINDOORLOC = SHARED_DATA / "ujiindoorloc"
