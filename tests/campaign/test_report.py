"""The field-health report from a store with two campaigns of the same field."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pihim.campaign.report import write_report
from pihim.campaign.store import open_store
from pihim.cli import main
from pihim.errors import PihimInputError


def _facets(rng, sigma):
    az = rng.standard_normal(25) * sigma
    el = rng.standard_normal(25) * sigma
    return [{"id": k + 1, "used": k != 12, "reason": None if k != 12 else "saturated",
             "az_mrad": float(az[k] - az.mean()), "el_mrad": float(el[k] - el.mean()), "az_sigma_mrad": 0.1,
             "el_sigma_mrad": 0.1, "points": 30} for k in range(25)]


def _rms(f):
    a = np.array([(x["az_mrad"], x["el_mrad"]) for x in f if x["used"]])
    return float(np.sqrt(np.mean(a**2)))


@pytest.fixture()
def store_two_campaigns(tmp_path):
    from pihim.field import nsttf_like_field

    fld = nsttf_like_field()
    piv = np.asarray(fld.pivots, float)
    hel = [(n, *piv[i]) for i, n in enumerate(fld.names)]
    rng = np.random.default_rng(1)
    path = tmp_path / "c.sqlite"
    truth = {}
    with open_store(path) as s:
        for camp, worse in (("2021-04", None), ("2021-05", "5E3")):
            cid = s.ensure_campaign(camp, field_source="nsttf-like", field_key="nsttf", heliostats=hel)
            for name in ("5E1", "5E3", "6W4"):
                f = _facets(rng, 3.0 if name == worse else 0.8)
                s.record_heliostat(cid, name, f, frame_ids=[f"fl/{name}"], parameters={"x": 1}, rms_mrad=_rms(f),
                                   frames=2)
                truth[(camp, name)] = f
        s.ensure_campaign("other-field", field_source="x", field_key="other", heliostats=hel[:3])
    return path, truth


def test_report_ranks_and_compares(store_two_campaigns, tmp_path) -> None:
    path, truth = store_two_campaigns
    with open_store(path) as s:
        summary = write_report(s, tmp_path / "r", campaign="2021-05")
    assert summary["compared_with"] == "2021-04"
    assert summary["heliostats_measured"] == 3 and summary["heliostats"] == 218
    assert summary["worst"][0]["name"] == "5E3"
    want = sorted(((n, _rms(truth[("2021-05", n)])) for n in ("5E1", "5E3", "6W4")), key=lambda kv: -kv[1])
    assert [w["name"] for w in summary["worst"]] == [n for n, _ in want]
    ch = {c["name"]: c for c in summary["changes"]}
    assert summary["changes"][0]["name"] == "5E3" and ch["5E3"]["delta"] > 0
    d = np.array([(a["az_mrad"] - b["az_mrad"], a["el_mrad"] - b["el_mrad"])
                  for a, b in zip(truth[("2021-05", "5E1")], truth[("2021-04", "5E1")], strict=True) if a["used"]])
    assert ch["5E1"]["facet_change_rms_mrad"] == pytest.approx(float(np.sqrt(np.mean(d**2))), abs=1e-4)
    index = (tmp_path / "r" / "index.html").read_text()
    assert "Worst heliostats" in index and 'href="heliostats/5E3.html"' in index and "change.png" in index
    page = (tmp_path / "r" / "heliostats" / "5E3.html").read_text()
    assert "fl/5E3" in page and "SAT" in page
    assert (tmp_path / "r" / "heliostats" / "5E3.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "r" / "report.json").read_text())["campaign"] == "2021-05"


def test_report_first_campaign_has_no_change(store_two_campaigns, tmp_path) -> None:
    path, _ = store_two_campaigns
    with open_store(path) as s:
        summary = write_report(s, tmp_path / "r", campaign="2021-04")
        assert summary["compared_with"] is None and "change" not in summary["files"]
        with pytest.raises(PihimInputError, match="different fields"):
            write_report(s, tmp_path / "r2", campaign="2021-05", compare="other-field")
        with pytest.raises(PihimInputError, match="no campaign"):
            write_report(s, tmp_path / "r3", campaign="nope")


def test_report_cli_json(store_two_campaigns, tmp_path, capsys) -> None:
    path, _ = store_two_campaigns
    assert main(["campaign", "report", str(path), "--out", str(tmp_path / "r"), "--campaign", "2021-05", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["schema"] == "pihim.campaign-report/1" and doc["worst"][0]["name"] == "5E3"
    assert main(["campaign", "report", str(tmp_path / "missing.sqlite"), "--out", str(tmp_path / "x")]) == 2


def _not_a_store(tmp_path, kind):
    path = tmp_path / f"{kind}.sqlite"
    if kind == "empty":
        path.write_bytes(b"")
    else:
        import sqlite3

        db = sqlite3.connect(path)
        db.execute("CREATE TABLE t (a)")
        db.commit()
        db.close()
    return path


@pytest.mark.parametrize("command", ["report", "export"])
@pytest.mark.parametrize("kind,msg", [("empty", "an empty file, not a campaign store"),
                                      ("foreign", "not a pihim campaign store")])
def test_report_and_export_refuse_a_non_store_and_leave_it_unchanged(tmp_path, capsys, command, kind, msg) -> None:
    """A 0-byte file used to become a 77 KB store (and export wrote header-only CSVs from it)."""
    path = _not_a_store(tmp_path, kind)
    before = path.read_bytes()
    assert main(["campaign", command, str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pihim: error: ") and msg in err[0]
    assert path.read_bytes() == before
    assert not (tmp_path / "out").exists()


def test_report_and_export_leave_the_store_byte_for_byte(store_two_campaigns, tmp_path) -> None:
    import hashlib

    path, _ = store_two_campaigns
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    assert main(["campaign", "report", str(path), "--out", str(tmp_path / "r")]) == 0
    assert main(["campaign", "export", str(path), "--out", str(tmp_path / "e")]) == 0
    assert (tmp_path / "r" / "index.html").is_file() and (tmp_path / "e" / "facets.csv").is_file()
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
