"""Artifacts (round trip, checksum refusal), loaders, evaluate CLI."""

import io

import numpy as np
import pytest

from localizer_tools import evaluate as evaluate_cli
from server.estimation.fingerprint import ArtifactError, checksum, evaluate, from_bytes, make_model, to_bytes
from server.estimation.fingerprint.artifact import MAGIC
from server.estimation.fingerprint.loaders import (
    read_survey_csv,
    read_uji_ble,
    read_ujiindoorloc,
    write_survey_csv,
)
from server.estimation.fingerprint.ujiindoorloc import UjiFormatError, parse_ujiindoorloc
from tests.helpers.synthetic import make_site


@pytest.fixture(scope="module")
def site_and_survey():
    site = make_site(seed=7, noise_db=1.0)
    return site, site.survey(scans_per_rp=4, seed=0)


@pytest.mark.parametrize("name", ["wknn", "knn", "nbc", "kde", "tkbe", "svm", "propagation"])
def test_artifact_round_trip(name, site_and_survey):
    site, fs = site_and_survey
    params = {"time_budget_s": 2.0, "C": 10.0} if name == "svm" else {}
    model = make_model(name, params, use_heading=True).fit(fs)
    blob = to_bytes(model)
    again = from_bytes(blob)
    assert type(again) is type(model) and again.get_params() == model.get_params()
    scans = site.survey(scans_per_rp=1, seed=3).scans()[:10]
    a, b = model.locate_many(scans, 90.0), again.locate_many(scans, 90.0)
    assert [(f.x, f.y, f.floor, f.reference_point) for f in a] == [(f.x, f.y, f.floor, f.reference_point) for f in b]
    assert len(checksum(blob)) == 64


def test_artifact_refuses_corruption(site_and_survey):
    _, fs = site_and_survey
    blob = to_bytes(make_model("knn").fit(fs))
    flipped = bytearray(blob)
    flipped[-20] ^= 0x01
    with pytest.raises(ArtifactError):
        from_bytes(bytes(flipped))
    with pytest.raises(ArtifactError):
        from_bytes(blob[:-1])  # truncated
    with pytest.raises(ArtifactError):
        from_bytes(b"XX" + blob[2:])  # bad header
    with pytest.raises(ArtifactError):
        from_bytes(b"")
    import hashlib
    import pickle

    payload = pickle.dumps({"not": "a model"})
    with pytest.raises(ArtifactError):
        from_bytes(MAGIC + hashlib.sha256(payload).digest() + payload)


def test_survey_csv_round_trip(tmp_path, site_and_survey):
    _, fs = site_and_survey
    path = tmp_path / "survey.csv"
    write_survey_csv(fs, path)
    back = read_survey_csv(path)
    assert back.tx_ids == fs.tx_ids
    assert np.array_equal(np.isnan(back.rss), np.isnan(fs.rss))
    assert np.allclose(np.nan_to_num(back.rss), np.nan_to_num(fs.rss), atol=1e-4)
    assert list(back.label) == list(fs.label) and np.allclose(back.heading_deg, fs.heading_deg, equal_nan=True)
    assert len(back.reference_points()) == len(fs.reference_points())


def test_read_ujiindoorloc_skips_silent_rows(tmp_path):
    head = "WAP001,WAP002,WAP003,LONGITUDE,LATITUDE,FLOOR,BUILDINGID,SPACEID,RELATIVEPOSITION,USERID,PHONEID,TIMESTAMP"
    rows = [
        "-60,100,-80,-7600.5,4864900.25,1,0,101,2,3,13,1371710000",
        "100,100,100,-7600.5,4864900.25,1,0,101,2,3,13,1371710001",
        "100,-70,100,-7610.0,4864910.0,2,1,102,2,4,14,1371710002",
    ]
    p = tmp_path / "uji.csv"
    p.write_text(head + "\n" + "\n".join(rows) + "\n")
    fs = read_ujiindoorloc(p)
    assert len(fs) == 2 and fs.meta["skipped"] == 1
    assert fs.tx_ids == ["wifi:wap001", "wifi:wap002", "wifi:wap003"]
    assert np.isnan(fs.rss[0, 1]) and fs.rss[0, 0] == -60
    assert list(fs.building) == [0, 1] and list(fs.floor) == [1, 2]
    assert list(fs.device) == ["phone-13", "phone-14"] and list(fs.user) == [3, 4] and fs.x[0] == -7600.5


def test_ujiindoorloc_parser_keeps_every_column_and_locates_errors():
    text = "WAP001,WAP002,LONGITUDE,LATITUDE,FLOOR,BUILDINGID,USERID,PHONEID,TIMESTAMP\n" \
           "-60,100,1.5,2.5,3,2,7,13,1371710000\n\n100,100,0,0,0,0,7,13,1\n-70,-80,1,2,0,1,8,14,2\n"
    survey = parse_ujiindoorloc(io.StringIO(text))
    assert survey.tx_ids == ["wifi:wap001", "wifi:wap002"] and survey.skipped == 1
    first, last = survey.records
    assert (first.x, first.y, first.floor, first.building, first.user, first.phone, first.timestamp) == (
        1.5, 2.5, 3, 2, 7, 13, 1371710000)
    assert first.rss == {"wifi:wap001": -60.0} and first.device == "phone-13"
    assert (last.row, last.line) == (3, 5)
    with pytest.raises(UjiFormatError) as bad:
        parse_ujiindoorloc(io.StringIO(text.replace("-70,-80,1,", "-70,-80,north,")))
    assert (bad.value.row, bad.value.line, bad.value.field) == (3, 5, "LONGITUDE")


def test_read_uji_ble(tmp_path):
    (tmp_path / "rss").mkdir()
    (tmp_path / "dep").mkdir()
    (tmp_path / "rss" / "lib_rss.csv").write_text("-60,100\n100,100\n-70,-80\n")
    (tmp_path / "rss" / "lib_crd.csv").write_text("1.0,2.0\n1.0,2.0\n3.0,4.0\n")
    (tmp_path / "rss" / "lib_ids.csv").write_text("12200101\n12200102\n22300201\n")
    (tmp_path / "dep" / "lib.csv").write_text("id,x,y\n23,0.5,0.5\n24,5.0,5.0\n")
    fs = read_uji_ble(tmp_path)
    assert fs.tx_ids == ["ble:lib23", "ble:lib24"] and len(fs) == 2 and fs.meta["skipped"] == 1
    assert list(fs.device) == ["phone-1", "phone-2"] and list(fs.user) == [2, 3]
    assert len(fs.reference_points()) == 2  # grouped by position


def test_evaluate_cli_prints_table(tmp_path, capsys, site_and_survey):
    _, fs = site_and_survey
    path = tmp_path / "s.csv"
    write_survey_csv(fs, path)
    rc = evaluate_cli.main([str(path), "--split", "phone", "--algorithms", "knn,nbc", "--kinds", "wifi,ble"])
    assert rc == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith(("knn", "nbc"))]
    assert len(lines) == 2


def test_evaluate_cli_shifts_the_test_readings(tmp_path, capsys, site_and_survey):
    """``--shift-db``: the held-out scans read louder; a model without an offset estimate
    (nbc, absolute dBm) answers worse, and the header says so."""
    _, fs = site_and_survey
    path = tmp_path / "s.csv"
    write_survey_csv(fs, path)
    means = {}
    for shift in ("0", "15"):
        assert evaluate_cli.main([str(path), "--split", "phone", "--algorithms", "nbc", "--shift-db", shift]) == 0
        out = capsys.readouterr().out
        assert ("shifted by +15 dB" in out) == (shift == "15")
        means[shift] = float(next(ln for ln in out.splitlines() if ln.startswith("nbc")).split()[1])
    assert means["15"] > means["0"]
    assert evaluate_cli.main([str(path), "--split", "phone", "--algorithms", "nbc", "--shift-db", "nan"]) == 2
    assert "--shift-db must be a finite number" in capsys.readouterr().err


def test_evaluate_cli_refuses_a_test_fraction_outside_0_1(tmp_path, capsys, site_and_survey):
    _, fs = site_and_survey
    path = tmp_path / "s.csv"
    write_survey_csv(fs, path)
    for fraction in ("0", "1", "1.5", "nan"):
        assert evaluate_cli.main([str(path), "--split", "random", "--algorithms", "nbc", "--test-fraction", fraction]) == 2
        assert f"--test-fraction must lie strictly between 0 and 1, not {float(fraction)}" in capsys.readouterr().err


def test_evaluate_on_an_empty_test_set_gives_nan_figures(site_and_survey):
    _, fs = site_and_survey
    metrics = evaluate(make_model("knn").fit(fs), fs.subset(np.zeros(len(fs), dtype=bool)))
    assert metrics.n_test == 0 and np.isnan(metrics.p90_error_m) and np.isnan(metrics.mapping_rate)


def test_loader_errors_are_clear_value_errors(tmp_path):
    from server.estimation.fingerprint.loaders import load

    with pytest.raises(ValueError, match="no such file"):
        load(tmp_path / "missing.csv", "csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(ValueError, match="lacks columns"):
        load(tmp_path / "empty.csv", "auto")
    (tmp_path / "bad.csv").write_text("x,y,floor,wifi:a\n1,2,0,-60\n1,2,0,loud\n")
    with pytest.raises(ValueError, match="data row 1, column wifi:a"):
        load(tmp_path / "bad.csv", "csv")
    with pytest.raises(ValueError, match="expects a directory"):
        load(tmp_path / "bad.csv", "ujible")
    (tmp_path / "rows.json").write_text('{"fingerprints": [{"x": 1}]}')
    with pytest.raises(ValueError, match="fingerprint 0 needs"):
        load(tmp_path / "rows.json", "auto")


def test_uji_ble_beacon_letters_and_power_groups(tmp_path):
    from server.estimation.fingerprint.loaders import load

    (tmp_path / "rss").mkdir()
    (tmp_path / "dep").mkdir()
    (tmp_path / "rss" / "lib_rss.csv").write_text("-60,100\n-65,-80\n-70,-80\n-71,-82\n")
    (tmp_path / "rss" / "lib_crd.csv").write_text("1.0,2.0\n1.0,2.0\n3.0,4.0\n3.0,4.0\n")
    (tmp_path / "rss" / "lib_ids.csv").write_text("12200101\n13200102\n22300201\n23300202\n")
    (tmp_path / "dep" / "lib.csv").write_text("id,x,y\nB1,0.5,0.5\nB22,5.0,5.0\n")
    fs = load(tmp_path, "auto")
    assert fs.tx_ids == ["ble:libb1", "ble:libb22"]
    assert list(fs.meta["power"]) == [2, 3, 2, 3]
    assert list(fs.subset(np.array([1, 3])).meta["power"]) == [3, 3]
    rc = evaluate_cli.main([str(tmp_path), "--split", "power", "--test-fraction", "0.5", "--algorithms", "wknn"])
    assert rc == 0


def test_evaluate_cli_says_error_and_exits_2(tmp_path, capsys, site_and_survey):
    _, fs = site_and_survey
    assert evaluate_cli.main([str(tmp_path / "nothing.csv")]) == 2
    assert "error:" in capsys.readouterr().err
    path = tmp_path / "s.csv"
    write_survey_csv(fs, path)
    assert evaluate_cli.main([str(path), "--split", "power"]) == 2  # no power column
    assert "no 'power' column" in capsys.readouterr().err
    (tmp_path / "one.csv").write_text("x,y,floor,device,wifi:a\n1,2,0,p,-60\n3,4,0,p,-70\n")
    assert evaluate_cli.main([str(tmp_path / "one.csv"), "--split", "phone"]) == 2  # one device only
    assert "same device" in capsys.readouterr().err
