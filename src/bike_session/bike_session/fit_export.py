"""A recorded session as a FIT activity file (``./bike report BAG --fit FILE``), for the tools
riders and trainer engineers already analyse rides with (Garmin Connect, Strava,
intervals.icu, GoldenCheetah). Written with Garmin's FIT SDK encoder (garmin-fit-sdk).

What goes in, per second of the session (the report's 1 s bins, bike_session.report):

- ``power`` [W]: the rider's mean mechanical power into the bike in that second (the report's
  rider power, from the plant's energy ledger), what a trainer's power meter reports;
- ``cadence`` [rpm]: the motor speed over ``load.gear_ratio``;
- ``speed`` [m/s] and ``distance`` [m]: the road speed the trainer shows, the controller's
  virtual speed (ControllerStatus.virtual_speed_mps: the virtual bike's in slope mode, else
  the cadence through the virtual gear in force and the wheel), as the report's distance
  uses (an older bag without it: the cadence through ``modes.virtual_gear_ratio``), and its
  integral;
- ``heart_rate`` [bpm]: the rider's mean heart rate in that second (PlantState.heart_rate_bpm),
  only in the seconds that have one (none: no rider, a prime mover, an older bag).

Messages: file_id (type activity), a timer start event, the records, a timer stop event, a
lap per workout segment (where SessionStatus.segment_index changed, as a head unit running a
structured workout starts a lap per step; ``wkt_step_index`` = the segment; one lap for a
bag without SessionStatus), one session (sport cycling, sub-sport indoor cycling) and the
activity, each lap and the session with its totals (time, distance, work, mean and max
power, cadence and speed; mean and max heart rate where the records have one). Time starts
at the session's ``start_wall_time`` (session_info), else at the bag's own start. A second
without any PlantState in the bag gets no record (a gap, as a head unit's pause). No rclpy
import here.
"""
from __future__ import annotations

import datetime
import math
import pathlib

import numpy as np

from bike_session.bags import BagError, read_topic, stamp_s
from bike_session.report import SESSION_STATES, SessionData, analyse, series

MAX_RECORDS = 7 * 24 * 3600       # one record per second: a week of riding


def activity_arrays(data: SessionData) -> dict:
    """Per-second arrays (t_s from the session start: the end of the record's second, FIT's
    whole-second stamp; start_s, end_s: the part of it ridden, width_s its length, power_w, cadence_rpm, speed_mps, distance_m,
    heart_rate_bpm: 0 where none) of the seconds that hold data. The last second counts only as
    far as the ride went: counted whole, a ride ending at x.5 s overstated work and timer by
    half a second of riding (a 1 ms ride exported "1 s, 0.7 kJ")."""
    s = series(data, points=None, merge=max(1, int(round(1.0 / data.bin_s))))
    keep = np.flatnonzero(np.nan_to_num(s["p_rider"], nan=-1.0) > -1.0)     # bins with PlantStates
    speed = np.nan_to_num(s["road_mps"])        # through the virtual gear in force (report)
    width = s["bin_s"]
    t_start = np.arange(len(speed)) * width
    ride_end_s = math.inf
    if data.first and data.summary.get("duration_s") is not None:
        ride_end_s = data.first["t"] + data.summary["duration_s"] - data.origin_s   # the last PlantState
    t_end = np.maximum(np.minimum(t_start + width, ride_end_s), t_start)
    widths = t_end - t_start
    distance = np.cumsum(speed * widths)
    return {"t_s": t_start[keep] + width, "start_s": t_start[keep], "end_s": t_end[keep], "width_s": widths[keep],
            "power_w": np.clip(np.nan_to_num(s["p_rider"][keep]), 0.0, None),
            "cadence_rpm": np.abs(np.nan_to_num(s["cadence"][keep])), "speed_mps": speed[keep],
            "distance_m": distance[keep], "heart_rate_bpm": np.nan_to_num(s["heart_rate"][keep]),
            "bin_s": width}


def segment_starts(data: SessionData) -> list[tuple[float, int]]:
    """(t_s from the session start, segment index) where a running session entered a segment
    (SessionStatus), in time order; empty for a bag without SessionStatus."""
    out: list[tuple[float, int]] = []
    for msg in sorted(read_topic(data.path, "session_status"), key=stamp_s):
        if SESSION_STATES.get(msg.state) != "RUNNING":
            continue
        if not out or msg.segment_index != out[-1][1]:
            out.append((stamp_s(msg) - data.origin_s, int(msg.segment_index)))
    return out


def _start_time(data: SessionData) -> datetime.datetime:
    text = (data.info or {}).get("start_wall_time")
    if isinstance(text, str):
        try:
            t = datetime.datetime.fromisoformat(text)
            return t if t.tzinfo else t.replace(tzinfo=datetime.timezone.utc)
        except ValueError:
            pass
    stat = pathlib.Path(str(data.path)).stat()
    return datetime.datetime.fromtimestamp(stat.st_mtime, tz=datetime.timezone.utc)


def fit_activity_bytes(data: SessionData) -> tuple[bytes, dict]:
    """The FIT activity of an analysed session, and its totals (what the lap / session say)."""
    try:
        from garmin_fit_sdk import Encoder, Profile
    except ImportError:
        raise BagError("writing FIT files needs Garmin's FIT SDK: pip install garmin-fit-sdk (make setup installs "
                       "it)", data.path) from None

    a = activity_arrays(data)
    n = len(a["t_s"])
    if n == 0:
        raise BagError("no PlantState in the bag: nothing to export", data.path)
    if n > MAX_RECORDS:
        raise BagError(f"{n} seconds of riding is beyond the export's {MAX_RECORDS} records", data.path)
    start = _start_time(data)
    power = np.rint(a["power_w"]).astype(int)
    cadence = np.rint(a["cadence_rpm"]).astype(int)
    # FIT's uint8 bpm (255: invalid); a second without a heart rate gets no field
    heart_bpm = np.clip(np.rint(a["heart_rate_bpm"]), 0, 254).astype(int)
    starts = segment_starts(data)
    # the lap of each record: the segment its second began in (one lap without SessionStatus)
    edges = np.array([t for t, _ in starts[1:]])
    lap_of = np.searchsorted(edges, a["start_s"] + 1e-6, side="right")
    laps = [np.flatnonzero(lap_of == j) for j in range(len(starts) or 1)]
    laps = [(j, idx) for j, idx in enumerate(laps) if idx.size]
    session = _totals(a, np.arange(n), start)
    end = session["end"]
    mesg = Profile["mesg_num"]
    enc = Encoder()
    enc.write_mesg({"mesg_num": mesg["FILE_ID"], "type": "activity", "manufacturer": "development", "product": 0,
                    "serial_number": 1, "time_created": start})
    enc.write_mesg({"mesg_num": mesg["EVENT"], "timestamp": start, "event": "timer", "event_type": "start"})
    for k in range(n):
        heart = {"heart_rate": int(heart_bpm[k])} if heart_bpm[k] > 0 else {}
        enc.write_mesg({"mesg_num": mesg["RECORD"], "timestamp": start + datetime.timedelta(seconds=float(a["t_s"][k])),
                        "power": int(power[k]), "cadence": int(min(cadence[k], 254)),
                        "speed": float(a["speed_mps"][k]), "distance": float(a["distance_m"][k]), **heart})
    enc.write_mesg({"mesg_num": mesg["EVENT"], "timestamp": end, "event": "timer", "event_type": "stop_all"})
    for k, (j, idx) in enumerate(laps):
        lap = _totals(a, idx, start)
        extra = {"wkt_step_index": starts[j][1]} if starts else {}
        enc.write_mesg({"mesg_num": mesg["LAP"], "message_index": k, "timestamp": lap["end"], "event": "lap",
                        "event_type": "stop", **_fit_totals(lap), **extra})
    enc.write_mesg({"mesg_num": mesg["SESSION"], "message_index": 0, "timestamp": end, "event": "session",
                    "event_type": "stop", "first_lap_index": 0, "num_laps": len(laps), "trigger": "activity_end",
                    **_fit_totals(session)})
    enc.write_mesg({"mesg_num": mesg["ACTIVITY"], "timestamp": end, "total_timer_time": session["timer_s"],
                    "num_sessions": 1, "type": "manual", "event": "activity", "event_type": "stop"})
    totals = {k: v for k, v in session.items() if k not in ("start", "end")}
    totals.update(start_time=start.isoformat(), records=n, laps=len(laps))
    return enc.close(), totals


def _totals(a: dict, idx: np.ndarray, session_start: datetime.datetime) -> dict:
    """Totals of the records idx (consecutive seconds of one lap, or all of them): from the
    start of the first record's second (``start``) to the end of the last one's (``end``); sums
    and means over the time each record covers."""
    p, c, v = a["power_w"][idx], a["cadence_rpm"][idx], a["speed_mps"][idx]
    w = a["width_s"][idx]
    hr = a["heart_rate_bpm"][idx]
    hr = hr[hr >= 0.5]                      # the records that carry one
    t0, t1 = float(a["start_s"][idx[0]]), float(a["end_s"][idx[-1]])
    timer_s = float(np.sum(w))

    def mean(x):
        return float(np.sum(x * w) / timer_s) if timer_s > 0 else float(np.mean(x))
    distance0_m = float(a["distance_m"][idx[0] - 1]) if idx[0] > 0 else 0.0
    return {"start": session_start + datetime.timedelta(seconds=t0),
            # FIT stamps whole seconds: the last record's, so that no record comes after the end
            "end": session_start + datetime.timedelta(seconds=float(a["t_s"][idx[-1]])),
            "elapsed_s": t1 - t0, "timer_s": timer_s,
            "distance_m": float(a["distance_m"][idx[-1]] - distance0_m), "work_j": float(np.sum(p * w)),
            "avg_power_w": mean(p), "max_power_w": float(np.max(p)),
            "avg_cadence_rpm": mean(c), "max_cadence_rpm": float(np.max(c)),
            "avg_speed_mps": mean(v), "max_speed_mps": float(np.max(v)),
            "avg_heart_rate_bpm": float(np.mean(hr)) if hr.size else None,
            "max_heart_rate_bpm": float(np.max(hr)) if hr.size else None}


def _fit_totals(t: dict) -> dict:
    """A lap's or the session's totals as FIT fields (heart rate only when it has one)."""
    heart = {"avg_heart_rate": int(round(min(t["avg_heart_rate_bpm"], 254))),
             "max_heart_rate": int(round(min(t["max_heart_rate_bpm"], 254)))} if t["avg_heart_rate_bpm"] else {}
    return {"start_time": t["start"], "total_elapsed_time": t["elapsed_s"], "total_timer_time": t["timer_s"],
            "total_distance": t["distance_m"], "total_work": int(round(t["work_j"])),
            "avg_power": int(round(t["avg_power_w"])), "max_power": int(round(t["max_power_w"])),
            "avg_cadence": int(round(min(t["avg_cadence_rpm"], 254))),
            "max_cadence": int(round(min(t["max_cadence_rpm"], 254))),
            "avg_speed": t["avg_speed_mps"], "max_speed": t["max_speed_mps"],
            "sport": "cycling", "sub_sport": "indoor_cycling", **heart}


def export_fit(bag_path, out_path, data: SessionData | None = None) -> dict:
    """Write a bag's FIT activity to ``out_path``; returns the totals. ``data``: the bag already
    analysed (reused when its bins make whole seconds, else the bag is read again with 1 s
    bins). BagError on a bag that cannot be read (or holds no ride), OSError on a file that
    cannot be written."""
    per_s = 1.0 / data.bin_s if data is not None else 0.0
    if data is None or data.bin_s > 1.0 or abs(per_s - round(per_s)) > 1e-9:
        data = analyse(bag_path, bin_s=1.0)
    payload, totals = fit_activity_bytes(data)
    pathlib.Path(out_path).write_bytes(payload)
    totals["bytes"] = len(payload)
    return totals


def format_totals(totals: dict) -> str:
    return (f"{totals['records']} records over {totals['elapsed_s']:.0f} s in {totals['laps']} "
            f"lap{'s' if totals['laps'] != 1 else ''}, "
            f"{totals['distance_m'] / 1000.0:.2f} km, {totals['work_j'] / 1000.0:.1f} kJ, "
            f"mean {totals['avg_power_w']:.0f} W / {totals['avg_cadence_rpm']:.0f} rpm")
