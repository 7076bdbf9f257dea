"""benchmarks/study_highdyn.py: its readings and the report it builds from finished campaigns."""

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import study_highdyn as study  # noqa: E402

from ultratight.receiver.cli.metrics import PAPER_TABLE3  # noqa: E402


def _campaign(cells, lost=0, duration_s=60.0):
    """A campaign.json summary whose channel-0 Doppler RMS per method are ``cells``."""
    meth = {m: {"doppler_rms_hz": v, "doppler_rms_hz_channel": v, "code_rms_chips": [0.01, 0.01, 0.01],
                "lock_lost_channels": lost, "noise_events": []} for m, v in cells.items()}
    return {"summary": {"runs": 10, "duration_s": duration_s, "channel": 0, "methods": meth,
                        "paper_table3": PAPER_TABLE3}}


def test_readings_cover_the_issue_grid():
    r = study.readings()
    for f in ("2", "3", "4.47", "10", "20"):
        assert r[f"if-x{f}"][1]["noise_events"][0]["noise_factor"] == float(f)
        assert r[f"corr-x{f}"][1]["noise_events"][0]["place"] == "correlator"
    assert r["filter-r-x4.47"][1]["noise_events"][0]["place"] == "filter-r"
    assert r["if-x20-coast"][1]["engine.lock_monitor"] is True


def test_paper_values_give_distance_zero_and_the_paper_order():
    _, score = study.table("x", "paper", _campaign({m: v["doppler_rms_hz"] for m, v in PAPER_TABLE3.items()}))
    # the paper's diverged cells passed as "no epochs" are left out; every other cell matches
    assert score["distance"] == 0.0
    assert score["ordered"] is True                    # 0.1125 < 0.5345 < 0.9153 < 1.8706


def test_distance_is_mean_abs_log10_ratio_and_order_breaks():
    cells = {m: [10 * x if x is not None else None for x in v["doppler_rms_hz"]] for m, v in PAPER_TABLE3.items()}
    cells["dlb-rackf"] = [1.0, 1.22, 2.455]            # x8.89, x10, x10 of the paper's
    _, score = study.table("x", "ten times", _campaign(cells))
    known = sum(x is not None for v in PAPER_TABLE3.values() for x in v["doppler_rms_hz"])   # 10 of 12 cells
    # RACKF: log10(1/0.1125) + 1 + 1; the other known cells 1 each; the two without epochs left out
    expect = (math.log10(1.0 / 0.1125) + 2.0 + (known - 3) * 1.0) / known
    assert score["distance"] == pytest.approx(expect, rel=1e-12)
    assert score["ordered"] is True
    cells["dlb-rackf"] = [6.0, 1.22, 2.455]            # RACKF worse than CKF (5.345) in 0-20 s
    assert study.table("x", "", _campaign(cells))[1]["ordered"] is False


def test_a_cell_the_paper_marks_diverged_counts_one_and_a_short_cut_only_its_segment():
    cells = {m: list(v["doppler_rms_hz"]) for m, v in PAPER_TABLE3.items()}
    cells["pb-kf-utc"][2] = 5.0                       # paper: diverged in 40-60 s; ours in lock
    known = sum(x is not None for v in PAPER_TABLE3.values() for x in v["doppler_rms_hz"])
    assert study.table("x", "", _campaign(cells))[1]["distance"] == pytest.approx(1.0 / (known + 1))
    short = {m: [10 * v["doppler_rms_hz"][0], None, None] for m, v in PAPER_TABLE3.items()}
    assert study.table("x", "", _campaign(short, duration_s=20.0))[1]["distance"] == pytest.approx(1.0)


def test_report_rebuilds_the_overview_from_campaign_files(tmp_path):
    (tmp_path / "if-x20").mkdir()
    (tmp_path / "if-x20" / "campaign.json").write_text(
        json.dumps(_campaign({m: v["doppler_rms_hz"] for m, v in PAPER_TABLE3.items()}, lost=3)))
    assert study.main(["--report", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "study.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| `if-x20`"))
    assert "| 10 × 60 |" in row and "| 0.113 (3) | 0.534 (3) | 0.915 (3) | 1.871 (3) |" in row and row.rstrip().endswith("| 0.00 | yes |")
    assert json.loads((tmp_path / "study.json").read_text())["if-x20"]["distance"] == 0.0
    assert study.main(["--report", "--out", str(tmp_path / "empty")]) == 1
