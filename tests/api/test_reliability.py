"""Reliability over real HTTP: idempotency bound to the request, races that never answer 500,
parser errors that are 422 naming the row."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.conftest import ADMIN_KEY

AP = "wifi:aa:bb:cc:dd:ee:01"


@pytest.fixture
def site(admin) -> dict:
    return admin.post("/api/v1/sites", json={"name": "Reliable", "floors": [{"level": 0}]}).json()


def url(site: dict) -> str:
    return f"/api/v1/sites/{site['id']}/surveys"


def survey(*labels: str, rss: float = -60.0) -> dict:
    return {"fingerprints": [{"x": float(i), "y": 1.0, "floor": 0, "label": label, "rss": {AP: rss}}
                             for i, label in enumerate(labels)]}


def stored(admin, site: dict) -> int:
    return admin.get(f"/api/v1/sites/{site['id']}").json()["fingerprints"]["survey"]


def test_an_idempotency_key_with_another_body_is_409_and_stores_nothing(admin, site):
    assert admin.post(url(site), json=survey("A"), headers={"Idempotency-Key": "k1"}).status_code == 201
    other = admin.post(url(site), json=survey("A", "B"), headers={"Idempotency-Key": "k1"})
    assert other.status_code == 409 and "another request" in other.json()["detail"]
    same = admin.post(url(site), json=survey("A"), headers={"Idempotency-Key": "k1"})
    assert same.status_code == 200 and same.headers["Idempotent-Replay"] == "true"
    assert stored(admin, site) == 1


def test_the_same_key_sent_concurrently_stores_once_and_replays(live_server, admin, site):
    def post(_: int) -> httpx.Response:
        with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"}, timeout=60) as c:
            return c.post(url(site), json=survey(*(f"P{i}" for i in range(50))), headers={"Idempotency-Key": "same"})

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(post, range(16)))
    assert sorted(a.status_code for a in answers) == [200] * 15 + [201], [a.text for a in answers if a.status_code >= 300]
    assert stored(admin, site) == 50


def test_concurrent_uploads_sharing_reference_points_never_answer_500(live_server, admin, site):
    def post(n: int) -> httpx.Response:
        with httpx.Client(base_url=live_server.url, headers={"Authorization": f"Bearer {ADMIN_KEY}"}, timeout=60) as c:
            body = survey(*(f"P{i}" for i in range(30)), rss=-40.0 - n)
            body["fingerprints"][0]["rss"] = {f"wifi:new{n % 3}": -50.0}  # transmitters first heard concurrently too
            return c.post(url(site), json=body)

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(post, range(20)))
    assert [a.status_code for a in answers] == [201] * 20, [a.text for a in answers if a.status_code != 201]
    points = admin.get(f"/api/v1/sites/{site['id']}/reference-points").json()
    assert len(points) == 30 and all(p["fingerprints"] == 20 for p in points)


def test_rows_of_a_source_file_are_stored_once_whatever_the_chunking(admin, site):
    labels = [f"R{i}" for i in range(10)]
    whole = survey(*labels)["fingerprints"]

    def chunk(first: int, end: int) -> httpx.Response:
        return admin.post(url(site), json={"fingerprints": whole[first:end]}, params={"source": "file-1", "first_row": first})

    assert chunk(0, 3).json()["accepted"] == 3
    again = chunk(2, 7)
    assert again.status_code == 201 and again.json()["accepted"] == 4 and again.json()["already_stored"] == 1
    rest = chunk(0, 10).json()
    assert rest["accepted"] == 3 and rest["already_stored"] == 7
    none_left = chunk(0, 10).json()
    assert none_left["accepted"] == 0 and none_left["already_stored"] == 10
    assert stored(admin, site) == 10
    other_file = admin.post(url(site), json={"fingerprints": whole[:2]}, params={"source": "file-2", "first_row": 0})
    assert other_file.json()["accepted"] == 2 and stored(admin, site) == 12


CSV_HEADER = "x,y,floor,label,wifi:ap1\n"


@pytest.mark.parametrize("body, row", [
    (CSV_HEADER.replace("\n", "\r") + "1,2,0,A,-50\r2,2,0,B,-50\r", None),  # CR-only line ends: the header's
    (CSV_HEADER + "1,2,0,A,-50\n2,2,0,B\r,-50\n", 1),  # a bare CR in a cell
    (CSV_HEADER + "1,2,0,A,-50\n1,2,0," + "L" * 140_000 + ",-50\n", 1),  # a cell over 128 KiB
    (CSV_HEADER + '1,2,0,A,-50\n1,2,0,"unterminated,-50\n' + "9,9,0,Z,-50\n" * 2, 1),
])
def test_unreadable_csv_is_422_naming_the_row_and_stores_nothing(admin, site, snapshot, body, row):
    before = snapshot()
    answer = admin.post(url(site), content=body.encode(), headers={"Content-Type": "text/csv"})
    assert answer.status_code == 422, answer.text
    detail = answer.json()["detail"]
    assert isinstance(detail, list) and detail[0]["row"] == row and "msg" in detail[0] and "type" in detail[0]
    assert snapshot() == before


def test_deeply_nested_json_is_422(admin, site):
    body = b'{"fingerprints": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    answer = admin.post(url(site), content=body, headers={"Content-Type": "application/json"})
    assert answer.status_code == 422 and "nested" in answer.text


def test_a_ujiindoorloc_file_cut_inside_its_last_cell_is_refused(admin, site):
    from pathlib import Path

    text = (Path(__file__).parent.parent / "fixtures" / "uji_tiny.csv").read_text()
    answer = admin.post(url(site), content=text[:-3].encode(), params={"format": "ujiindoorloc"},
                        headers={"Content-Type": "text/csv"})
    assert answer.status_code == 422 and "truncated" in answer.text
    assert stored(admin, site) == 0


# --- bad input that used to be a 500, and limits ------------------------------------------------

BIG = 2**63


@pytest.mark.parametrize("path", [f"/api/v1/sites/{BIG}", f"/api/v1/sites/{2**31}/models",
                                  f"/api/v1/sites/1/models/{BIG}", f"/api/v1/sites/{-BIG - 1}/reference-points"])
def test_ids_beyond_the_databases_integer_range_in_a_path_are_422(admin, path):
    answer = admin.get(path)
    assert answer.status_code == 422 and answer.json()["detail"][0]["loc"][0] == "path"


def test_ids_beyond_the_databases_integer_range_in_a_body_or_query_are_422(admin, device, site):
    assert device.post("/api/v1/sessions", json={"site_id": BIG, "filter": "ekf"}).status_code == 422
    assert device.post("/api/v1/sessions", json={"site_id": site["id"], "filter": "ekf", "model_id": 2**31}).status_code == 422
    assert device.get("/api/v1/sessions", params={"site_id": 2**31}).status_code == 422
    assert device.post(f"/api/v1/sites/{site['id']}/locate", json={"rss": {AP: -50}, "model_id": BIG}).status_code == 422
    assert admin.post(url(site), json=survey("A"), params={"first_row": BIG}).status_code == 422


@pytest.mark.parametrize("make", [
    lambda site: ("POST", "/api/v1/sites", {"name": "nul\u0000name"}),
    lambda site: ("POST", url(site), {"fingerprints": [{"x": 0, "y": 0, "floor": 0, "rss": {AP: -50}, "label": "a\u0000"}]}),
    lambda site: ("POST", url(site), {"fingerprints": [{"x": 0, "y": 0, "floor": 0, "rss": {AP: -50}, "device": "\u0000"}]}),
])
def test_nul_characters_are_422_and_store_nothing(admin, site, snapshot, make):
    before = snapshot()
    method, path, body = make(site)
    answer = admin.request(method, path, json=body)
    assert answer.status_code == 422, answer.text
    assert all({"loc", "msg", "type"} <= set(e) for e in answer.json()["detail"])
    assert snapshot() == before


def test_a_session_id_with_a_nul_character_is_not_a_500(device):
    assert device.get("/api/v1/sessions/abc%00def").status_code in (404, 422)


def open_session(device, site) -> str:
    answer = device.post("/api/v1/sessions", json={"site_id": site["id"], "filter": "ekf",
                                                   "initial": {"x": 0, "y": 0, "floor": 0}})
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def test_times_beyond_1e12_seconds_are_422(device, site):
    session = open_session(device, site)
    step = {"t": 1e308, "length_m": 0.7, "heading_deg": 0}
    assert device.post(f"/api/v1/sessions/{session}/batches", json={"seq": 0, "steps": [step]}).status_code == 422
    step["t"] = 1.0
    assert device.post(f"/api/v1/sessions/{session}/batches", json={"seq": 0, "steps": [step]}).status_code == 200


def test_json_routes_refuse_another_content_type_with_415(device, site):
    session = open_session(device, site)
    body = b'{"seq": 0, "steps": [], "scans": []}'
    for content_type in ("text/plain", "application/x-www-form-urlencoded"):
        answer = device.post(f"/api/v1/sessions/{session}/batches", content=body, headers={"Content-Type": content_type})
        assert answer.status_code == 415, answer.text
    answer = device.post(f"/api/v1/sites/{site['id']}/locate", content=b'{"rss": {}}', headers={"Content-Type": "text/csv"})
    assert answer.status_code == 415
    assert device.post(f"/api/v1/sessions/{session}/batches", content=body,
                       headers={"Content-Type": "application/json; charset=utf-8"}).status_code == 200


def test_a_huge_batch_is_413_before_it_is_read(device, site):
    """A 60 MB batch (1.4 M steps) is refused as it arrives, declared or streamed, never parsed."""
    session = open_session(device, site)
    step = b'{"t": 1.0, "length_m": 0.7, "heading_deg": 0},'
    chunk = step * 10_000
    declared = device.post(f"/api/v1/sessions/{session}/batches", content=b'{"seq": 0, "steps": [' + chunk * 130 + b"]}",
                           headers={"Content-Type": "application/json"})
    assert declared.status_code == 413

    def stream():
        yield b'{"seq": 0, "steps": ['
        for _ in range(130):
            yield chunk

    streamed = device.post(f"/api/v1/sessions/{session}/batches", content=stream(), headers={"Content-Type": "application/json"})
    assert streamed.status_code == 413 and "exceeds 4194304 bytes" in streamed.text
    big_locate = device.post(f"/api/v1/sites/{site['id']}/locate", content=b'{"rss": {' + b" " * 300_000 + b"}}",
                             headers={"Content-Type": "application/json"})
    assert big_locate.status_code == 413
    full = {"seq": 0, "steps": [{"t": i, "length_m": 0.7, "heading_deg": 0} for i in range(1000)],
            "scans": [{"t": i + 0.5, "rss": {f"wifi:ap{j}": -60.0 for j in range(50)}} for i in range(1000)]}
    assert device.post(f"/api/v1/sessions/{session}/batches", json=full).status_code != 413  # the limit fits a full batch
