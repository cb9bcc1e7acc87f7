"""Training reads a site's fingerprints as a stream fetched in chunks, never as one list."""

from __future__ import annotations

import inspect

import numpy as np
from sqlalchemy import insert

from server.domain import FingerprintRecord
from server.estimation.fingerprint import FingerprintSet
from server.services.training import _row
from server.store import surveys
from server.tables import Fingerprint


def test_the_stream_yields_every_row_in_id_order_across_chunks(db, site_id):
    survey = [FingerprintRecord(float(i), 0.0, i % 2, {f"wifi:ap{i % 3}": -40.0 - i}, label=f"p{i}", device="d")
              for i in range(7)]
    with db.transaction() as s:
        surveys.add_survey(s, site_id, survey[:4], None, 0)
        s.execute(insert(Fingerprint), [
            {"site_id": site_id, "source": "crowd", "floor": 0, "x": 9.0, "y": 9.0, "rss": {"wifi:ap9": -60.0}}])
        surveys.add_survey(s, site_id, survey[4:], None, 0)
    with db.transaction() as s:
        stream = surveys.stream_training_rows(s, site_id, include_crowd=False, chunk=2)
        assert inspect.isgenerator(stream)
        streamed = list(stream)
        with_crowd = list(surveys.stream_training_rows(s, site_id, include_crowd=True, chunk=3))
        fs = FingerprintSet.from_rows((_row(r) for r in surveys.stream_training_rows(s, site_id, False, chunk=2)),
                                      dtype=np.float16)
    assert streamed == survey
    assert [r.x for r in with_crowd] == [0.0, 1.0, 2.0, 3.0, 9.0, 4.0, 5.0, 6.0]
    assert fs.rss.dtype == np.float16 and fs.tx_ids == ["wifi:ap0", "wifi:ap1", "wifi:ap2"]
    assert fs.rss[6, 0] == -46.0 and list(fs.label) == [f"p{i}" for i in range(7)]

