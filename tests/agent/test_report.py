from agent.report import detector_table, relative_gain, write_report


def _row(m50, m):
    return {"map50": m50, "map50_95": m}


def test_relative_gain_like_the_paper():
    assert relative_gain(0.62, 0.4) == "+55.0 %"
    assert relative_gain(0.3, 0.0) == "n/a (Real = 0)"
    assert relative_gain(None, 0.4) == "–"


def test_report_has_table_and_plot(tmp_path):
    table = {m: {"held-out real": _row(0.8, 0.5), "15 m": _row(0.7, 0.4), "50 m": _row(v, v / 2)}
             for m, v in (("real", 0.2), ("synthetic", 0.25), ("r+s", 0.3))}
    rows = detector_table(table)
    assert rows[0].startswith("| test set | real mAP50")
    assert any(r.startswith("| 50 m |") and "+50.0 %" in r for r in rows)
    out = write_report(tmp_path, {"eval": {"table": table}, "fit": {"heldout_psnr": 31.2}}, {"fit": 12.0}, 20.0)
    text = out.read_text()
    assert "31.20 dB" in text and "map_vs_altitude.png" in text
    assert (tmp_path / "derived" / "map_vs_altitude.png").is_file()
