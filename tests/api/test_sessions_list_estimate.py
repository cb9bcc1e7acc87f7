"""The session list reads each session's estimate from its track's last row (not from the
tracker state): it must equal the session's own estimate, whatever the filter and stage."""

from __future__ import annotations

import pytest

from tests.api.test_sessions import batch, open_session, positioning, site  # noqa: F401  (fixtures)


@pytest.mark.parametrize("name", ["kf", "ekf", "pf", "skpf"])
def test_the_listed_estimate_equals_the_sessions(device, admin, site, positioning, name):  # noqa: F811
    fresh = open_session(device, site, name)["id"]  # the initial estimate only, undated
    dated = open_session(device, site, name)["id"]  # a batch whose only scan gives no fix: the initial estimate dated
    assert device.post(f"/api/v1/sessions/{dated}/batches",
                       json={"seq": 0, "scans": [{"t": 3.0, "rss": {"wifi:free": -50}}]}).status_code == 200
    fed = open_session(device, site, name)["id"]
    scans = [{"t": 1.2, "rss": {"wifi:ap1": -50, "wifi:ap2": -60, "wifi:ap3": -60}}]
    for seq in range(3):
        assert device.post(f"/api/v1/sessions/{fed}/batches", json=batch(seq, 2.0 * seq, 3, scans if seq == 1 else None)
                           ).status_code == 200
    unstarted = open_session(device, site, name, initial=False)["id"]  # no position yet: null
    assert device.delete(f"/api/v1/sessions/{fed}").status_code == 204

    for client in (device, admin):
        listed = {s["id"]: s for s in client.get("/api/v1/sessions", params={"limit": 1000}).json()}
        assert set(listed) >= {fresh, dated, fed, unstarted}
        for sid in (fresh, dated, fed, unstarted):
            assert listed[sid] == device.get(f"/api/v1/sessions/{sid}").json(), sid
    assert listed[unstarted]["estimate"] is None
    assert listed[fed]["estimate"] == device.get(f"/api/v1/sessions/{fed}/track").json()[-1]
    assert listed[dated]["estimate"]["t"] == 3.0 and listed[fresh]["estimate"]["t"] is None
    # the filters still apply
    only_closed = client.get("/api/v1/sessions", params={"status": "closed"}).json()
    assert [s["id"] for s in only_closed] == [fed]
