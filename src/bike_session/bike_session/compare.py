"""A/B comparison of two recorded sessions (``./bike compare BAG_A BAG_B [--out DIR]``).

Both bags are read in one pass each (:func:`bike_session.report.analyse`, same bin width).
Every number is taken over the OVERLAPPING time range, time counted from the start of
each recording: a 5 s and a 3 s session are compared on 0..3 s, and the text says so.

Per session, over the overlap (definitions as in :mod:`bike_session.report`):

- ``duration_s``, ``mean_braking_power_w``, ``mean_rider_power_w``, ``mean_cadence_rpm``,
  ``distance_m`` (the virtual bike's road speed integrated: a gear or shifting change shows)
- ``energy_battery_j``, ``energy_resistor_j``, ``energy_loss_j``, ``energy_mech_in_j``: ledger
  at the end of the overlap minus the ledger at the first PlantState
- ``peak_phase_current_a``
- ``tracking``: per mode (ERG power, isokinetic cadence, resistance torque against Eq. 3-4,
  slope: the flywheel's road speed against the virtual bike's)
  RMS and max |error| over 0.1 s windows, and per batch
- ``erg_response``: ERG target steps, how many settled, median and max settle time
  (:func:`bike_session.report.erg_response`), when either session has a step
- ``shift_response``: slope-mode shifts, how many were felt at the cranks, median and max time,
  the largest overshoot (:func:`bike_session.report.shift_response`), when either session shifted
- ``mean_heart_rate_bpm``, ``max_heart_rate_bpm``: the rider's heart rate, when either session
  has one
- ``heart_rate_erg``: heart-rate ERG target stretches, how many settled (within 3 bpm), median and
  max settle time, mean and largest |error| after settling (:func:`bike_session.report.heart_rate_erg`),
  when either session has a stretch

``delta`` = B - A (``delta_pct`` relative to |A|). Same bag twice: every delta is 0.
The controller / config differences are the parameters that differ between the two
``config_text`` of session_info, plus a shortened unified diff of the texts.

Outputs with ``--out DIR``: compare.txt, compare.json, compare.html (charts embedded) and
overlay charts on the common time axis: compare_power.png, compare_cadence.png,
compare_torque.png, compare_battery_energy.png. Bad input: one error line, exit 2.
"""
from __future__ import annotations

import argparse
import difflib
import html
import json
import math
import pathlib
import sys

import numpy as np

from bike_session.bags import BagError, open_bag
from bike_session.report import (PLOT_POINTS, SessionData, analyse, auto_bin_s, config_params, erg_response,
                                  heart_rate_erg, heart_rate_figures, img_tag, series, shift_response, time_axis,
                                  tracking, write_html)

COLORS = {"A": "tab:blue", "B": "tab:orange"}
DIFF_LINES = 60
# (key, label, unit, digits)
METRICS = (
    ("duration_s", "duration", "s", 3),
    ("mean_braking_power_w", "mean braking power", "W", 2),
    ("mean_rider_power_w", "mean rider power", "W", 2),
    ("mean_cadence_rpm", "mean cadence", "rpm", 2),
    ("distance_m", "distance (virtual bike)", "m", 1),
    ("energy_battery_j", "energy into battery", "J", 2),
    ("energy_resistor_j", "energy into resistor", "J", 2),
    ("energy_loss_j", "energy losses", "J", 2),
    ("energy_mech_in_j", "energy from the rider", "J", 2),
    ("peak_phase_current_a", "peak phase current", "A", 2),
)
# (key, label, unit, digits): rows when either session has a heart rate
HEART_METRICS = (("mean_heart_rate_bpm", "mean heart rate", "bpm", 1),
                 ("max_heart_rate_bpm", "max heart rate", "bpm", 1))
TRACK_FIELDS = (("rms", "RMS error", 3), ("max_abs", "max |error|", 3), ("rms_batch", "RMS error per batch", 3),
                ("time_s", "time in mode", 3))
# (field of report.erg_response, label, unit, digits)
ERG_FIELDS = (("steps", "ERG target steps", "count", 0), ("settled", "ERG steps settled", "count", 0),
              ("median_s", "ERG settle time, median", "s", 2), ("max_s", "ERG settle time, max", "s", 2))
# (field of report.shift_response, label, unit, digits)
SHIFT_FIELDS = (("shifts", "slope shifts", "count", 0), ("settled", "shifts felt", "count", 0),
                ("median_s", "shift felt after, median", "s", 2), ("max_s", "shift felt after, max", "s", 2),
                ("overshoot_pct_max", "shift overshoot, max", "%", 0))
# (field of report.heart_rate_erg, label, unit, digits)
HR_ERG_FIELDS = (("stretches", "HR ERG target stretches", "count", 0),
                 ("settled", "HR ERG stretches settled", "count", 0),
                 ("median_settle_s", "HR ERG settle time, median", "s", 1),
                 ("max_settle_s", "HR ERG settle time, max", "s", 1),
                 ("mae_bpm", "HR ERG mean |error| after settling", "bpm", 2),
                 ("max_abs_bpm", "HR ERG max |error| after settling", "bpm", 2))


def range_metrics(d: SessionData, n: int) -> dict:
    """The session's numbers over bins 0..n-1 (see the module docstring)."""
    b = {k: v[:n] for k, v in d.bins.items()}
    dur = float(b["dt"].sum())
    out = {key: None for key, *_ in METRICS}
    out["duration_s"] = dur
    if dur > 0:
        out["mean_braking_power_w"] = float(b["e_brake"].sum() / dur)
        out["mean_rider_power_w"] = float(b["e_mech"].sum() / dur)
        out["mean_cadence_rpm"] = float(b["rpm_dt"].sum() / dur / d.machine["gear_ratio"])
        out["distance_m"] = float(b["road_m"].sum())
    for key, col in (("energy_battery_j", "E_bat"), ("energy_resistor_j", "E_res"), ("energy_loss_j", "E_loss"),
                     ("energy_mech_in_j", "E_mech")):
        v = b[col][np.isfinite(b[col])]
        if v.size and d.first:
            out[key] = float(v[-1] - d.first[col])
    ipk = b["ipk"][np.isfinite(b["ipk"])]
    out["peak_phase_current_a"] = float(ipk.max()) if ipk.size else None
    out["tracking"] = tracking(d.bins, d.bin_s, n)
    out["erg_response"] = erg_response(d.bins, d.bin_s, n)
    out["shift_response"] = shift_response(d.bins, d.origin_s, d.bin_s, d.shifts, n)
    out["mean_heart_rate_bpm"], out["max_heart_rate_bpm"] = heart_rate_figures(d.bins, n)
    out["heart_rate_erg"] = heart_rate_erg(d.bins, d.origin_s, d.bin_s, d.hr_stretches, n)
    return out


def _delta(a, b):
    if a is None or b is None:
        return None, None
    delta = b - a
    pct = 100.0 * delta / abs(a) if a else (0.0 if delta == 0 else None)
    return delta, pct


def _same_file(key: str, va, vb, path_a, path_b) -> bool:
    """Whether a file parameter (session.profile ...) names the same file on both sides: a config
    copy (./bike run --set, --calibration) names it absolute, its source relative to its folder."""
    from bike_plant.config import RELATIVE_FILE_KEYS, resolve_config_path

    if key not in {".".join(k) for k in RELATIVE_FILE_KEYS} or not (isinstance(va, str) and isinstance(vb, str)):
        return False
    if not (va and vb and path_a and path_b):
        return False
    return resolve_config_path(va, path_a).resolve() == resolve_config_path(vb, path_b).resolve()


def config_diff(text_a: str | None, text_b: str | None, path_a: str | None = None,
                path_b: str | None = None) -> dict:
    """Parameters that differ and a shortened unified diff of the two config texts (``path_a`` /
    ``path_b``: the configs' files, session_info's config_path, against which a relative file
    parameter is read)."""
    notes = []
    params = {}
    for side, text in (("a", text_a), ("b", text_b)):
        try:
            params[side] = config_params(text)
        except ValueError as exc:
            params[side] = {}
            notes.append(f"{side.upper()}: {exc}")
        if not text:
            notes.append(f"{side.upper()}: no config_text in session_info")
    missing = object()
    changed = []
    for key in sorted(set(params["a"]) | set(params["b"])):
        va, vb = params["a"].get(key, missing), params["b"].get(key, missing)
        if va != vb and not _same_file(key, va, vb, path_a, path_b):
            changed.append({"key": key, "a": None if va is missing else va, "b": None if vb is missing else vb,
                            "only_in": "b" if va is missing else ("a" if vb is missing else None)})
    lines = list(difflib.unified_diff((text_a or "").splitlines(), (text_b or "").splitlines(),
                                      "A config_text", "B config_text", n=1, lineterm=""))
    more = max(len(lines) - DIFF_LINES, 0)
    return {"identical_text": (text_a or "") == (text_b or ""), "parameters": changed,
            "text_diff": lines[:DIFF_LINES] + ([f"... ({more} more lines)"] if more else []), "notes": notes}


def _side(d: SessionData, n: int) -> dict:
    info = d.info or {}
    workout = info.get("workout") if isinstance(info.get("workout"), dict) else None
    return {
        "bag": str(d.path),
        "profile_name": d.summary.get("profile_name"),
        "software_version": info.get("software_version"),
        "config_path": info.get("config_path"),
        "workout": {k: workout.get(k) for k in ("workout_format", "ftp_w", "description") if k in workout}
        if workout else None,
        "recorded_duration_s": d.summary.get("duration_s"),
        "modes": d.summary.get("time_in_mode_s"),
        "machine": d.summary.get("machine"),
        "metrics": range_metrics(d, n),
        "warnings": d.summary.get("warnings"),
    }


def compare(bag_a, bag_b, progress: str | None = None) -> tuple[dict, SessionData, SessionData, int]:
    """(result dict, data A, data B, bins compared). Raises BagError."""
    spans = []
    for path in (bag_a, bag_b):
        with open_bag(path) as bag:
            spans.append(bag.duration_s)
    bin_s = max(auto_bin_s(s) for s in spans)
    da = analyse(bag_a, bin_s=bin_s, progress=progress)
    db = analyse(bag_b, bin_s=bin_s, progress=progress)
    for d in (da, db):
        if not d.summary.get("plant_states"):
            raise BagError("no PlantState messages: nothing to compare", d.path)
    na, nb = da.n_bins, db.n_bins
    n = min(na, nb)
    if n == 0:
        raise BagError("fewer than two PlantStates: nothing to compare", (db if nb == 0 else da).path)
    a, b = _side(da, n), _side(db, n)
    end_s = n * bin_s
    overlap = {"start_s": 0.0, "end_s": end_s, "bin_s": bin_s, "truncated": na != nb,
               "a_span_s": na * bin_s, "b_span_s": nb * bin_s}
    if na != nb:
        longer = "A" if na > nb else "B"
        overlap["note"] = (f"compared on the overlapping range 0-{end_s:g} s from the start of each recording "
                           f"(A {na * bin_s:g} s, B {nb * bin_s:g} s): the rest of {longer} is not compared")
    else:
        overlap["note"] = f"both sessions cover 0-{end_s:g} s from the start of their recording"
    metrics = []
    for key, label, unit, digits in METRICS:
        va, vb = a["metrics"][key], b["metrics"][key]
        delta, pct = _delta(va, vb)
        metrics.append({"key": key, "label": label, "unit": unit, "a": va, "b": vb, "delta": delta,
                        "delta_pct": pct, "digits": digits})
    if any(s["metrics"][key] is not None for s in (a, b) for key, *_ in HEART_METRICS):
        for key, label, unit, digits in HEART_METRICS:
            va, vb = a["metrics"][key], b["metrics"][key]
            delta, pct = _delta(va, vb)
            metrics.append({"key": key, "label": label, "unit": unit, "a": va, "b": vb, "delta": delta,
                            "delta_pct": pct, "digits": digits})
    track = {}
    ta, tb = a["metrics"]["tracking"], b["metrics"]["tracking"]
    for key in [k for k in ("erg_power", "isokinetic_cadence", "resistance_torque", "slope_speed", "cadence_target")
                if k in ta or k in tb]:
        ra, rb = ta.get(key) or {}, tb.get(key) or {}
        unit = (ra or rb)["unit"]
        entry = {"unit": unit, "compares": (ra or rb)["compares"], "a": ra or None, "b": rb or None}
        for field, label, digits in TRACK_FIELDS:
            delta, pct = _delta(ra.get(field), rb.get(field))
            entry[f"delta_{field}"] = delta
            metrics.append({"key": f"tracking.{key}.{field}", "label": f"{key} {label}",
                            "unit": "s" if field == "time_s" else unit, "a": ra.get(field), "b": rb.get(field),
                            "delta": delta, "delta_pct": pct, "digits": digits})
        track[key] = entry
    for name, fields in (("erg_response", ERG_FIELDS), ("shift_response", SHIFT_FIELDS),
                         ("heart_rate_erg", HR_ERG_FIELDS)):
        ea, eb = a["metrics"][name], b["metrics"][name]
        if not (ea or eb):
            continue
        for field, label, unit, digits in fields:
            # a side without a step / shift: 0 of them, no time
            va = (ea or {}).get(field, 0 if unit == "count" else None)
            vb = (eb or {}).get(field, 0 if unit == "count" else None)
            delta, pct = _delta(va, vb)
            metrics.append({"key": f"{name}.{field}", "label": label, "unit": unit, "a": va, "b": vb,
                            "delta": delta, "delta_pct": pct, "digits": digits})
    result = {
        "a": a, "b": b, "overlap": overlap, "metrics": metrics, "tracking": track,
        "config_diff": config_diff((da.info or {}).get("config_text"), (db.info or {}).get("config_text"),
                                   (da.info or {}).get("config_path"), (db.info or {}).get("config_path")),
        "same_software": a["software_version"] == b["software_version"],
    }
    return result, da, db, n


# ============================================================================ text

def _f(v, digits=3) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.{digits}f}"
    return str(v)


def format_compare(r: dict) -> str:
    a, b = r["a"], r["b"]
    lines = ["A/B comparison"]
    for side, s in (("A", a), ("B", b)):
        lines.append(f"{side}: {s['bag']}")
        lines.append(f"   profile {s['profile_name']}, recorded {_f(s['recorded_duration_s'])} s, software "
                     f"{s['software_version']}, modes " + (", ".join(f"{k} {v:.1f} s" for k, v in (s['modes'] or {}).items())
                                                         or "n/a"))
    lines.append(("NOTE: " if r["overlap"]["truncated"] else "") + r["overlap"]["note"])
    lines.append("")
    lines.append(f"{'':<46} {'A':>13} {'B':>13} {'B - A':>13}")
    for m in r["metrics"]:
        d = m["digits"]
        pct = f"{m['delta_pct']:+.1f} %" if m["delta_pct"] is not None else ""
        # a space before each column: a figure as wide as its column ran into the one before
        # (a '+13796.5 %' read as part of the difference)
        lines.append(f"{(m['label'] + ' [' + m['unit'] + ']'):<46} {_f(m['a'], d):>13} {_f(m['b'], d):>13} "
                     f"{_f(m['delta'], d):>13} {pct:>10}".rstrip())
    for key, t in r["tracking"].items():
        lines.append(f"  {key}: {t['compares']} [{t['unit']}], 0.1 s windows")
    cd = r["config_diff"]
    lines.append("")
    if cd["identical_text"]:
        lines.append("config: identical config_text")
    else:
        lines.append(f"config: {len(cd['parameters'])} parameter(s) differ")
        for p in cd["parameters"]:
            # a key one config does not set is not one it sets to null (YAML's ~)
            va, vb = ("(not set)" if p["only_in"] == only else _short(p[side])
                      for only, side in (("b", "a"), ("a", "b")))
            lines.append(f"  {p['key']}: {va} -> {vb}")
        if cd["text_diff"]:
            lines.append("config_text diff (shortened):")
            lines += ["  " + ln for ln in cd["text_diff"]]
    for note in cd["notes"]:
        lines.append(f"  note: {note}")
    if not r["same_software"]:
        lines.append(f"software: {a['software_version']} -> {b['software_version']}")
    for side, s in (("A", a), ("B", b)):
        for w in s.get("warnings") or []:
            lines.append(f"warning ({side}): {w}")
    return "\n".join(lines)


def _short(v, limit: int = 60) -> str:
    text = json.dumps(v) if not isinstance(v, str) else v
    return text if len(text) <= limit else text[:limit - 3] + "..."


# ============================================================================ charts

def plot_compare(da: SessionData, db: SessionData, n: int, out: pathlib.Path) -> list[pathlib.Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    top = max(da.n_bins, db.n_bins)
    k = max(1, math.ceil(top / PLOT_POINTS))
    sa, sb = series(da, merge=k), series(db, merge=k)
    span = top * da.bin_s
    end = n * da.bin_s
    _, unit = time_axis(np.zeros(1), span)
    scale = 60.0 if unit == "min" else 1.0
    xlabel = f"time since the start of the recording [{unit}]"
    labels = {"A": f"A: {da.summary.get('profile_name') or ''} [{da.name}]",
              "B": f"B: {db.summary.get('profile_name') or ''} [{db.name}]"}
    written = []

    def figure(name, title, ylabel, draw):
        fig, ax = plt.subplots(figsize=(10, 4.8))
        for side, s in (("A", sa), ("B", sb)):
            draw(ax, s, side)
        if end < span - 1e-9:
            ax.axvspan(end / scale, span / scale, color="gray", alpha=0.12, label="outside the overlap")
        ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        written.append(out / name)

    def power(ax, s, side):
        ax.plot(s["t"] / scale, s["p_brake"], color=COLORS[side], label=f"{labels[side]} braking power")
        if np.isfinite(s["erg_target"]).any():
            ax.plot(s["t"] / scale, s["erg_target"], color=COLORS[side], ls="--", lw=1, label=f"{side} ERG target")

    def cadence(ax, s, side):
        ax.plot(s["t"] / scale, s["cadence"], color=COLORS[side], label=labels[side])
        if np.isfinite(s["iso_target"]).any():
            ax.plot(s["t"] / scale, s["iso_target"], color=COLORS[side], ls="--", lw=1,
                    label=f"{side} isokinetic target")

    def torque(ax, s, side):
        ax.plot(s["t"] / scale, s["torque"], color=COLORS[side], label=labels[side])

    def energy(ax, s, side):
        ax.plot(s["t"] / scale, s["E_bat"], color=COLORS[side], label=f"{labels[side]} battery")
        if np.nanmax(np.abs(np.nan_to_num(s["E_res"]))) > 0:
            ax.plot(s["t"] / scale, s["E_res"], color=COLORS[side], ls=":", label=f"{side} brake resistor")

    figure("compare_power.png", "Braking power (-T_em w), A vs B", "power [W]", power)
    figure("compare_cadence.png", "Crank cadence, A vs B", "cadence [rpm]", cadence)
    figure("compare_torque.png", "Braking torque -T_em, A vs B", "torque [N m]", torque)
    figure("compare_battery_energy.png", "Energy into the battery since start, A vs B", "energy [J]", energy)
    return written


# ============================================================================ files / CLI

def _json_ready(r: dict) -> dict:
    return json.loads(json.dumps(r, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def write_outputs(result: dict, da: SessionData, db: SessionData, n: int, out_dir) -> list[pathlib.Path]:
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    text = format_compare(result)
    (out / "compare.json").write_text(json.dumps(_json_ready(result), indent=2) + "\n")
    (out / "compare.txt").write_text(text + "\n")
    written = [out / "compare.json", out / "compare.txt"]
    pngs = plot_compare(da, db, n, out)
    written += pngs
    rows = ["<tr><th></th><th>A</th><th>B</th><th>B - A</th><th></th></tr>"]
    for m in result["metrics"]:
        d = m["digits"]
        pct = f"{m['delta_pct']:+.1f} %" if m["delta_pct"] is not None else ""
        rows.append(f"<tr><td>{html.escape(m['label'])} [{html.escape(m['unit'])}]</td><td>{_f(m['a'], d)}</td>"
                    f"<td>{_f(m['b'], d)}</td><td>{_f(m['delta'], d)}</td><td>{pct}</td></tr>")
    body = [f"<h1>A/B comparison: {html.escape(da.name)} vs {html.escape(db.name)}</h1>",
            f"<p>{html.escape(result['overlap']['note'])}</p>",
            "<table>" + "".join(rows) + "</table>",
            f"<h2>Details</h2><pre>{html.escape(text)}</pre>"]
    body += [img_tag(p) for p in pngs]
    write_html(out / "compare.html", f"bike compare {da.name} {db.name}", "\n".join(body))
    written.append(out / "compare.html")
    return written


def main(argv=None) -> int:
    """``bike compare BAG_A BAG_B [--json] [--out DIR]``; bad input: one error line, exit 2."""
    parser = argparse.ArgumentParser(prog="bike compare", description="Compare two recorded bike sessions (A/B).")
    parser.add_argument("bag_a", help="session A: bag directory or .mcap file")
    parser.add_argument("bag_b", help="session B: bag directory or .mcap file")
    parser.add_argument("--out", help="write compare.txt/.json/.html and overlay charts (PNG) into this folder")
    parser.add_argument("--json", action="store_true", help="print the comparison as JSON")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.out:
        from bike_session.cli import output_dir
        if output_dir(args.out, "--out") is None:       # before the bags are read: one error, no work lost
            return 2
    try:
        result, da, db, n = compare(args.bag_a, args.bag_b, progress="bike compare")
        written = write_outputs(result, da, db, n, args.out) if args.out else []
    except BagError as exc:
        print(f"bike compare: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bike compare: error: cannot write to {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(json.dumps(_json_ready(result), indent=2) if args.json else format_compare(result))
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
