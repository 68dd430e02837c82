"""Paper 001 Table 1 (section 7, Fig. 11-16): predictive vs PI, simulated (bike_session.paper_spmsm).

The rows the simulation reproduces are checked against the paper within a factor of 2; the
rows it misses are checked against the documented band of what it achieves now (no xfail),
so a change that moves them shows up here. Misses, and why (see paper_spmsm / the report):
- sine / triangle, predictive: 5-6 r/min vs 12 / 28 (ours better: the one-step law sees the
  command one sample ahead; what is left is friction and cogging at the zero crossings);
- THD, both: ~1 % / ~2 % vs 8.8 / 12.5 % (5 % / 3 % back-EMF harmonics and 1.5 us dead time
  are rejected by current loops of ~2 kHz / 200 Hz; the order of the paper's figures would
  need ~10x the harmonic voltage);
- Fig. 14 linearity, predictive: the 15 A current limit turns steps >= 50 r/min into ramps,
  cogging and Coulomb friction dominate 2-10 r/min.
"""
from __future__ import annotations

import csv
import math
import pathlib

import numpy as np
import pytest

from bike_session import paper_spmsm as P

ROOT = pathlib.Path(__file__).resolve().parents[1]
CFG_PATH = ROOT / "config" / "spmsm_default.yaml"

ROWS = [("step_200", "rise_time"), ("step_200", "settling_time"), ("load_step", "speed_drop"),
        ("load_step", "recovery_time"), ("sine", "max_tracking_error"), ("triangle", "max_tracking_error"),
        ("steps", "linearity"), ("thd", "phase_current_thd")]


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    out = tmp_path_factory.mktemp("seed2")
    res = P.table1(CFG_PATH, out)
    with open(out / "table1.csv") as fh:
        rows = list(csv.DictReader(fh))
    return res, {(r["experiment"], r["metric"]): r for r in rows}, out


@pytest.mark.slow
def test_table1_writes_every_row_and_figure(table):
    res, rows, out = table
    with open(out / "table1.csv") as fh:
        header = next(csv.reader(fh))
    assert header[:7] == ["experiment", "metric", "unit", "predictive", "pi", "paper_predictive", "paper_pi"]
    assert {"within_factor_2", "winner_ok", "ratio_predictive", "ratio_pi"} <= set(header)
    assert list(rows) == ROWS
    for key in ROWS:
        assert math.isfinite(float(rows[key]["predictive"])) and math.isfinite(float(rows[key]["pi"]))
    for key, (pp, ppi) in P.PAPER.items():
        assert (float(rows[key]["paper_predictive"]), float(rows[key]["paper_pi"])) == (pp, ppi)
    assert res["name"] == "seed2-table1" and len(res["rows"]) == len(ROWS)
    names = sorted(pathlib.Path(f).name for f in res["files"])
    assert names == ["seed2_fig11.png", "seed2_fig12.png", "seed2_fig13.png", "seed2_fig14.png",
                     "seed2_fig15_16.png", "table1.csv"]
    for f in res["files"]:
        assert pathlib.Path(f).stat().st_size > 1000
    # not every row is reproduced (module docstring): the verdict says so
    assert res["passed"] is False
    text = P.summary(res)
    assert text.startswith("seed2-table1: FAIL") and len(text.splitlines()) == 2 + len(ROWS)


@pytest.mark.slow
def test_predictive_wins_every_row_the_paper_says_it_wins(table):
    _, rows, _ = table
    for key in ROWS:
        if key == ("steps", "linearity"):
            continue                                   # a criterion row, below
        r = rows[key]
        assert float(r["predictive"]) < float(r["pi"]), key
        assert r["winner_ok"] == "yes", key


@pytest.mark.slow
def test_rows_within_a_factor_of_2_of_the_paper(table):
    """Load step (drop and recovery, both families) and the PI's tracking errors."""
    _, rows, _ = table
    for key in (("load_step", "speed_drop"), ("load_step", "recovery_time")):
        assert 0.5 <= float(rows[key]["ratio_predictive"]) <= 2.0, key
        assert 0.5 <= float(rows[key]["ratio_pi"]) <= 2.0, key
        assert rows[key]["within_factor_2"] == "yes"
    for key in (("sine", "max_tracking_error"), ("triangle", "max_tracking_error")):
        assert 0.5 <= float(rows[key]["ratio_pi"]) <= 2.0, key
    # the two calibrated unknowns (observer pole, PI poles) put the load step here
    drop = rows[("load_step", "speed_drop")]
    assert 20.0 < float(drop["predictive"]) < 32.0 and 45.0 < float(drop["pi"]) < 70.0


@pytest.mark.slow
def test_missed_rows_stay_in_their_documented_bands(table):
    """Rows outside the factor of 2, pinned to what the simulation achieves (ratios ours/paper)."""
    _, rows, _ = table
    sine, tri = rows[("sine", "max_tracking_error")], rows[("triangle", "max_tracking_error")]
    assert 0.3 <= float(sine["ratio_predictive"]) < 0.5 and sine["within_factor_2"] == "no"
    assert 0.1 <= float(tri["ratio_predictive"]) < 0.4 and tri["within_factor_2"] == "no"
    thd = rows[("thd", "phase_current_thd")]
    assert 0.05 <= float(thd["ratio_predictive"]) < 0.25 and 0.05 <= float(thd["ratio_pi"]) < 0.3
    assert thd["within_factor_2"] == "no"
    lin = rows[("steps", "linearity")]
    assert float(lin["predictive"]) > P.LINEARITY_TOL_PERCENT and lin["winner_ok"] == "no"


def test_tracking_commands_and_helpers():
    t = np.linspace(0.0, 2.0, 2001)
    sine = P.tracking_command("sine")(t)
    tri = P.tracking_command("triangle")(t)
    assert sine[0] == 0.0 and tri[0] == pytest.approx(0.0, abs=1e-12)
    assert sine.max() == pytest.approx(200.0, rel=1e-4) and tri.max() == pytest.approx(200.0)
    assert tri.min() == pytest.approx(-200.0)
    slope = np.diff(tri) / np.diff(t)
    assert np.all(np.isclose(np.abs(slope), 800.0) | (np.abs(slope) < 800.0))   # 4 A / T, corners
    with pytest.raises(ValueError):
        P.tracking_command("square")
    x = np.arange(10.0)
    assert np.allclose(P._moving_mean(x, 3)[1:-1], x[1:-1])
    # the CSV row verdicts
    row = P._row("load_step", "speed_drop", "r/min", 25.0, 60.0)
    assert row["ratio_predictive"] == 1.25 and row["ratio_pi"] == 1.5 and row["within_factor_2"] and row["winner_ok"]
    row = P._row("thd", "phase_current_thd", "%", 1.0, 2.0)
    assert row["within_factor_2"] is False and row["winner_ok"] is True
