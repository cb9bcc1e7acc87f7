"""Survey / track / crowd clients against an in-memory fake of API.md (httpx.MockTransport).

The real live-server test belongs to the integrator; these check what the clients
send (paths, auth, bodies, seq handling) and that they survive flaky posts.
"""

import asyncio
import itertools
import json

import httpx

from client_sim.phone import simulate_phone
from client_sim.report import write_report
from client_sim.runs import run_survey, run_track, session_seed, survey_fingerprints
from client_sim.world import open_room


class FakeServer:
    """Just enough of API.md: keys, sites, surveys, models, sessions with seq dedup."""

    def __init__(self, fail_every: int = 0):
        self.sites, self.sessions, self.models, self.requests = {}, {}, {}, []
        self.ids = itertools.count(1)
        self.fail_every, self.batch_posts = fail_every, 0

    def handler(self, request: httpx.Request) -> httpx.Response:
        key = request.headers.get("authorization", "")
        path, method = request.url.path, request.method
        body = json.loads(request.content) if request.content else None
        self.requests.append((method, path, key, body))
        if key not in ("Bearer admin", "Bearer device"):
            return httpx.Response(401, json={"detail": "unknown key"})
        admin_only = path.startswith("/api/v1/sites") and not path.endswith("/locate")
        if admin_only and key != "Bearer admin":
            return httpx.Response(403, json={"detail": "admin scope"})
        parts = path.strip("/").split("/")[2:]
        if parts == ["sites"] and method == "POST":
            sid = str(next(self.ids))
            self.sites[sid] = dict(body, id=sid, fingerprints=[])
            return httpx.Response(201, json={"id": sid, "name": body["name"]})
        if parts[0] == "sites" and len(parts) == 2:
            s = self.sites[parts[1]]
            return httpx.Response(200, json={"id": s["id"], "fingerprints": len(s["fingerprints"])})
        if parts[0] == "sites" and parts[2] == "surveys":
            self.sites[parts[1]]["fingerprints"] += body["fingerprints"]
            labels = {f["label"] for f in body["fingerprints"]}
            return httpx.Response(201, json={"accepted": len(body["fingerprints"]), "reference_points": len(labels)})
        if parts[0] == "sites" and parts[2] == "models" and len(parts) == 3:
            mid = str(next(self.ids))
            self.models[mid] = {"id": mid, "algorithm": body["algorithm"], "status": "ready", "active": True}
            return httpx.Response(202, json=dict(self.models[mid], status="queued"))
        if parts[0] == "sites" and parts[2] == "models":
            return httpx.Response(200, json=self.models[parts[3]])
        if parts[0] == "sites" and parts[2] == "locate":
            return httpx.Response(200, json={"x": 1.0, "y": 1.0, "floor": 0, "covariance": [[1, 0], [0, 1]]})
        if parts == ["sessions"]:
            sid = str(next(self.ids))
            init = body.get("initial") or {"x": 0.0, "y": 0.0, "floor": 0}
            self.sessions[sid] = {"body": body, "applied": {}, "track": [], "pos": [init["x"], init["y"], init["floor"]]}
            return httpx.Response(201, json={"id": sid, "site_id": body["site_id"], "filter": body["filter"]})
        if parts[0] == "sessions" and len(parts) == 3 and parts[2] == "batches":
            self.batch_posts += 1
            if self.fail_every and self.batch_posts % self.fail_every == 0:
                return httpx.Response(503, json={"detail": "try again"})
            s = self.sessions[parts[1]]
            if body["seq"] in s["applied"]:
                return httpx.Response(200, json=s["applied"][body["seq"]])
            if s["applied"] and body["seq"] < max(s["applied"]):
                return httpx.Response(409, json={"detail": "seq"})
            import math
            for st in body["steps"]:  # a perfect PDR integrator stands in for the tracker
                h = math.radians(st["heading_deg"])
                s["pos"][0] += st["length_m"] * math.sin(h)
                s["pos"][1] += st["length_m"] * math.cos(h)
            ts = [x["t"] for x in body["steps"] + body["scans"]] or [0.0]
            est = {"t": max(ts), "x": s["pos"][0], "y": s["pos"][1], "floor": s["pos"][2],
                   "covariance": [[1, 0], [0, 1]], "source": "step"}
            s["track"].append(est)
            res = {"seq": body["seq"], "estimate": est, "applied_steps": len(body["steps"]),
                   "applied_scans": len(body["scans"])}
            s["applied"][body["seq"]] = res
            return httpx.Response(200, json=res)
        if parts[0] == "sessions" and parts[-1] == "track":
            return httpx.Response(200, json=self.sessions[parts[1]]["track"])
        if parts[0] == "sessions" and method == "DELETE":
            return httpx.Response(204)
        return httpx.Response(404, json={"detail": f"no route {method} {path}"})


def test_survey_creates_site_uploads_four_headings_and_trains():
    fake = FakeServer()
    res = asyncio.run(run_survey("http://x", "admin", "open_room", scans_per_heading=2, train="knn",
                                 transport=httpx.MockTransport(fake.handler)))
    world = open_room()
    create = fake.requests[0]
    assert create[:3] == ("POST", "/api/v1/sites", "Bearer admin")
    assert len(create[3]["transmitters"]) == len(world.transmitters) and create[3]["floors"][0]["walls"]
    fps = fake.sites[res["site_id"]]["fingerprints"]
    assert res["accepted"] == len(fps) == len(world.reference_points) * 4 * 2
    assert {f["heading_deg"] for f in fps} == {0.0, 90.0, 180.0, 270.0}
    assert all(f["rss"] and all(-130 <= v <= 0 for v in f["rss"].values()) for f in fps)
    assert all(k.startswith(("wifi:", "ble:")) for f in fps for k in f["rss"])
    assert res["model"]["status"] == "ready"


def test_survey_is_deterministic():
    assert survey_fingerprints(open_room(), 1, seed=3) == survey_fingerprints(open_room(), 1, seed=3)
    assert survey_fingerprints(open_room(), 1, seed=3) != survey_fingerprints(open_room(), 1, seed=4)


def test_batches_cover_every_step_and_scan_once_with_increasing_seq():
    trace = simulate_phone(open_room(), open_room().routes[0], seed=1)
    batches = [b.to_api() for b in trace.batches(2.0)]
    assert [b["seq"] for b in batches] == list(range(len(batches)))
    assert sum(len(b["steps"]) for b in batches) == len(trace.steps)
    assert sum(len(b["scans"]) for b in batches) == len(trace.scans)
    times = [x["t"] for b in batches for x in b["steps"]]
    assert times == sorted(times)


def test_track_retries_failed_posts_with_the_same_seq(tmp_path):
    fake = FakeServer(fail_every=5)
    res = asyncio.run(run_track("http://x", "device", "open_room", "1", phones=3, filters=["skpf", "ekf"],
                                seed=2, transport=httpx.MockTransport(fake.handler)))
    assert [p["filter"] for p in res["phones"]] == ["skpf", "ekf", "skpf"]
    for phone in res["phones"]:
        assert phone["failed_posts"] == 0
        sent = [r[3]["seq"] for r in fake.requests if r[1] == f"/api/v1/sessions/{phone['session_id']}/batches"]
        assert sorted(set(sent)) == list(range(max(sent) + 1))  # every seq, in order
        assert len(sent) > len(set(sent))  # some were re-sent after a 503 ...
        assert len(fake.sessions[phone["session_id"]]["applied"]) == len(set(sent))  # ... and applied once
        assert phone["batch_estimates"] and phone["track"]
        # the fake tracker is pure PDR from the true start: errors stay those of PDR
        assert max(e["error_m"] for e in phone["track"]) < 15
    opened = [r[3] for r in fake.requests if r[1] == "/api/v1/sessions"]
    assert all(o["initial"]["floor"] == 0 for o in opened)
    # every session seeded, each phone its own seed, the same ones for the same run seed
    assert sorted(o["seed"] for o in opened) == sorted(session_seed(2, i) for i in range(3))
    assert len({o["seed"] for o in opened}) == 3 and all(0 <= o["seed"] < 2**32 for o in opened)
    assert session_seed(2, 0) != session_seed(3, 0)
    path = tmp_path / "r.json"
    path.write_text(json.dumps(res))
    table = write_report([path], tmp_path / "rep")
    assert set(table["open_room"]) == {"skpf", "ekf", "pdr-only"}
    assert (tmp_path / "rep" / "cdf.png").stat().st_size > 1000
    assert (tmp_path / "rep" / "trajectory.png").exists()


def test_wrong_key_is_an_error_not_a_silent_pass():
    fake = FakeServer()
    import pytest

    from client_sim.http_client import ApiError
    with pytest.raises(ApiError) as e:
        asyncio.run(run_survey("http://x", "nope", "open_room", scans_per_heading=1,
                               transport=httpx.MockTransport(fake.handler)))
    assert e.value.status == 401
