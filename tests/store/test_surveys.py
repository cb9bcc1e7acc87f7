"""Survey storage: reference points keyed by label or position, idempotent uploads, training rows."""

from __future__ import annotations

import pytest
from sqlalchemy import insert
from sqlalchemy.exc import IntegrityError

from server.domain import FingerprintRecord, ReferencePointSummary, SurveyOutcome, Transmitter
from server.store import sites, surveys
from server.tables import Fingerprint


def fp(x: float, y: float, floor: int = 0, label: str | None = None, **extra) -> FingerprintRecord:
    return FingerprintRecord(x, y, floor, {"wifi:ap1": -50.0, "ble:b1": -70.0}, label=label, **extra)


def test_fingerprints_share_a_reference_point_by_position_to_the_millimetre(db, site_id):
    with db.transaction() as s:
        survey = [fp(1.0001, 2.0), fp(1.0004, 2.0), fp(1.0006, 2.0), fp(1.0001, 2.0, floor=1)]
        first = surveys.add_survey(s, site_id, survey, None, 0)
    assert first == SurveyOutcome(accepted=4, reference_points=3, new_reference_points=3)
    with db.transaction() as s:
        again = surveys.add_survey(s, site_id, [fp(1.0, 2.0), fp(9.0, 9.0)], None, 2)
    assert again == SurveyOutcome(accepted=2, reference_points=2, new_reference_points=1, skipped=2)
    with db.transaction() as s:
        points = surveys.reference_points(s, site_id)
    assert [(p.floor, p.x, p.fingerprints) for p in points] == [(0, 1.0001, 3), (0, 1.0006, 1), (0, 9.0, 1), (1, 1.0001, 1)]


def test_a_labelled_reference_point_sits_at_the_mean_of_its_fingerprints(db, site_id):
    with db.transaction() as s:
        surveys.add_survey(s, site_id, [fp(0.0, 0.0, label="A1"), fp(2.0, 4.0, label="A1")], None, 0)
    with db.transaction() as s:
        outcome = surveys.add_survey(s, site_id, [fp(4.0, 2.0, label="A1"), fp(4.0, 2.0, floor=1, label="A1")], None, 0)
        points = surveys.reference_points(s, site_id)
    assert outcome.new_reference_points == 1  # A1 on floor 1; A1 on floor 0 exists
    assert points == [ReferencePointSummary("A1", 0, 2.0, 2.0, 3), ReferencePointSummary("A1", 1, 4.0, 2.0, 1)]


def test_a_survey_registers_the_transmitters_it_hears(db, site_id):
    with db.transaction() as s:
        surveys.add_survey(s, site_id, [fp(0.0, 0.0)], None, 0)
        assert sites.list_transmitters(s, site_id) == [Transmitter("ble:b1", "ble"), Transmitter("wifi:ap1", "wifi")]


def test_an_upload_is_found_again_by_its_idempotency_key(db, site_id):
    with db.transaction() as s:
        stored = surveys.add_survey(s, site_id, [fp(0.0, 0.0), fp(1.0, 0.0)], "upload-1", 5)
    with db.transaction() as s:
        replay = surveys.find_upload(s, site_id, "upload-1")
        assert replay == SurveyOutcome(accepted=2, reference_points=2, new_reference_points=2, skipped=5, replayed=True)
        assert stored.replayed is False
        assert surveys.find_upload(s, site_id, "upload-2") is None
    with pytest.raises(IntegrityError), db.transaction() as s:
        surveys.add_survey(s, site_id, [fp(0.0, 0.0)], "upload-1", 0)


def test_training_rows_are_the_fingerprints_with_their_labels(db, site_id):
    survey = [fp(0.0, 0.0, label="A1", heading_deg=-90.0, t=1.5, device="pixel"), fp(3.0, 4.0, floor=1)]
    with db.transaction() as s:
        surveys.add_survey(s, site_id, survey, None, 0)
        s.execute(insert(Fingerprint), [
            {"site_id": site_id, "source": "crowd", "floor": 0, "x": 7.0, "y": 7.0, "rss": {"wifi:ap1": -60.0}}
        ])
    with db.transaction() as s:
        rows = list(surveys.stream_training_rows(s, site_id, include_crowd=False))
        with_crowd = list(surveys.stream_training_rows(s, site_id, include_crowd=True))
    assert rows == [  # headings are stored in [0, 360)
        FingerprintRecord(0.0, 0.0, 0, survey[0].rss, heading_deg=270.0, t=1.5, device="pixel", label="A1"),
        FingerprintRecord(3.0, 4.0, 1, survey[1].rss),
    ]
    assert with_crowd == [*rows, FingerprintRecord(7.0, 7.0, 0, {"wifi:ap1": -60.0})]
