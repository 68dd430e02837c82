"""Paper 001 Table 1 (section 7, Fig. 11-16): predictive vs PI, simulated (bike_session.paper_spmsm).

The rows the simulation reproduces are checked against the paper within a factor of 2; the
rows it misses are checked against the documented band of what it achieves now (no xfail),
so a change that moves them shows up here. Speeds are the encoder's per 1 ms speed sample
(the DSP's measured speed, 6 r/min resolution). Misses, and why (see paper_spmsm):
- triangle, predictive: ~11 r/min vs 28 (the law sees the command one sample ahead and the
  observer feeds the torque forward: the corners cost nothing; the paper's loop met them as
  a disturbance);
- THD, both: ~1 % / ~2 % vs 8.8 / 12.5 % (the current loops reject the EMF harmonics and the
  dead time; the paper's level needs ~2-3 V of 5th / 7th voltage; overmodulation, modelled
  by inverter.overmodulation: clamp, gives only ~1.7 / ~2.3 %: the loops correct the clipping);
- Fig. 14 linearity, predictive: from 50 to 350 r/min the steps share one shape (the speed
  law's reference trajectory); the 2 and 10 r/min steps ride cogging and Coulomb friction
  (15-65 % overshoot) and keep the row above its 10 % criterion.
"""
from __future__ import annotations

import csv
import math
import pathlib
import re

import numpy as np
import pytest

from bike_plant.config import config_variant
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
    """Load step (drop and recovery, both families), the sine (both) and the PI's triangle."""
    _, rows, _ = table
    for key in (("load_step", "speed_drop"), ("load_step", "recovery_time"), ("sine", "max_tracking_error")):
        assert 0.5 <= float(rows[key]["ratio_predictive"]) <= 2.0, key
        assert 0.5 <= float(rows[key]["ratio_pi"]) <= 2.0, key
        assert rows[key]["within_factor_2"] == "yes"
    assert 0.5 <= float(rows[("triangle", "max_tracking_error")]["ratio_pi"]) <= 2.0
    # the two calibrated unknowns (observer pole, PI poles) put the load step here
    drop = rows[("load_step", "speed_drop")]
    assert 20.0 < float(drop["predictive"]) < 34.0 and 45.0 < float(drop["pi"]) < 75.0


@pytest.mark.slow
def test_missed_rows_stay_in_their_documented_bands(table):
    """Rows outside the factor of 2, pinned to what the simulation achieves (ratios ours/paper)."""
    _, rows, _ = table
    tri = rows[("triangle", "max_tracking_error")]
    assert 0.3 <= float(tri["ratio_predictive"]) < 0.5 and tri["within_factor_2"] == "no"
    thd = rows[("thd", "phase_current_thd")]
    assert 0.05 <= float(thd["ratio_predictive"]) < 0.25 and 0.05 <= float(thd["ratio_pi"]) < 0.3
    assert thd["within_factor_2"] == "no"
    lin = rows[("steps", "linearity")]
    assert 30.0 < float(lin["predictive"]) < 120.0 and lin["winner_ok"] == "no"
    assert float(lin["predictive"]) < float(lin["pi"])
    # ... but linear from 50 r/min up (without the reference trajectory: from no step)
    down_to = re.search(r"within 10 % down to (\S+) / ", lin["note"]).group(1)
    assert float(down_to) <= 50.0, lin["note"]


def test_measured_speed_is_the_encoder_count_per_sample():
    """M method on the recorded count: 6 r/min steps for 10000 counts/rev and 1 ms records."""
    t = np.arange(6) * 1e-3
    out = {"t": t, "encoder_count": np.array([0.0, 33.0, 67.0, 100.0, 133.0, 167.0]),
           "speed_rpm": np.full(6, 200.0)}
    m = P.measured_speed_rpm(out, {"encoder": {"pulses_per_rev": 2500, "quadrature": 4}})
    assert m[0] == 200.0
    assert np.allclose(m[1:], [198.0, 204.0, 198.0, 198.0, 204.0])


def test_linearity_measure_compares_shapes_on_their_own_time_axis():
    """Two first-order responses of different time constants are one shape (0 %); an
    overshooting one deviates; one that never reaches 90 % has no shape."""
    t = np.linspace(0.0, 2.0, 2001)
    a = P.normalised_shape(t, 1.0 - np.exp(-t / 0.05))
    b = P.normalised_shape(t, 1.0 - np.exp(-t / 0.2))
    assert np.max(np.abs(a - b)) < 0.01
    wn, z = 60.0, 0.2
    wd = wn * math.sqrt(1 - z * z)
    ring = 1.0 - np.exp(-z * wn * t) * (np.cos(wd * t) + z / math.sqrt(1 - z * z) * np.sin(wd * t))
    c = P.normalised_shape(t, ring)
    assert np.max(np.abs(c - a)) > 0.3
    assert P.normalised_shape(t, 0.5 * (1.0 - np.exp(-t / 0.05))) is None


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


@pytest.mark.slow
def test_overmodulation_does_not_raise_the_thd_to_the_papers_level():
    """inverter.overmodulation: clamp (voltage limit 2 Vdc/pi, per-phase duty clamp) at 200 r/min
    and 1 N m: less flux-weakening current and more 5th / 7th voltage; the predictive family's
    THD rises (0.9 -> 2.0 %), the PI's falls with its smaller fundamental (1.8 -> 1.6 %; 2.3 %
    while the switching model lost a leg's dead time past the carrier's end), both below half
    the paper's 8.8 / 12.5 % (why: paper_spmsm docstring)."""
    cfg = config_variant(P._load(CFG_PATH), inverter={"overmodulation": "clamp"})
    base = P._load(CFG_PATH)
    for fam, paper in zip(P.FAMILIES, P.PAPER[("thd", "phase_current_thd")]):
        lin, om = P.current_thd(base, fam), P.current_thd(cfg, fam)
        assert abs(om["speed_rpm"] - P.SPEED_RPM) < 3.0
        assert om["id"] > lin["id"] + 0.5                       # less flux weakening
        assert om["thd_percent"] < 0.5 * paper
        if fam == "predictive":
            assert om["thd_percent"] > lin["thd_percent"] + 0.5


@pytest.mark.parametrize("config", ["bldc_default.yaml", "bldc_can.yaml"])
def test_paper_001_on_the_bldc_bike_is_one_error_naming_the_machine(config, tmp_path, capsys):
    """seed2-table1 with a BLDC config said "machine: expected 'spmsm' for this loader, got
    'bldc'" (the loader is nothing a user asked for): one error now says which bike the command
    reproduces, as the seed1-* commands do for an SPMSM config, and nothing is written."""
    from bike_session import cli

    out = tmp_path / "out"
    assert cli.main(["paper", "seed2-table1", "--config", str(ROOT / "config" / config), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "'bldc' bike" in err and "paper 001" in err and "loader" not in err, err
    assert not any(out.glob("*")) if out.exists() else True
