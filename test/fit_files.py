"""FIT workout files for the tests, written with Garmin's FIT SDK encoder (the same SDK the
reader decodes with, so the bytes are what a Garmin tool writes: header, definition and data
records, both CRCs).

``python test/fit_files.py`` rewrites test/data/workouts/sweet_spot.fit from SWEET_SPOT.
"""
from __future__ import annotations

import datetime
import pathlib

# FIT workout_power: <= 1000 percent of FTP, > 1000 watts + 1000
SWEET_SPOT = [
    dict(wkt_step_name="Warm up", duration_type="time", duration_value=300_000, target_type="power", target_value=0,
         custom_target_value_low=50, custom_target_value_high=60, intensity="warmup", notes="Easy spin to start"),
    dict(wkt_step_name="Sweet spot", duration_type="time", duration_value=480_000, target_type="power",
         target_value=0, custom_target_value_low=88, custom_target_value_high=92, intensity="active",
         secondary_target_type="cadence", secondary_custom_target_value_low=85,
         secondary_custom_target_value_high=95),
    dict(wkt_step_name="Recover", duration_type="time", duration_value=120_000, target_type="power", target_value=0,
         custom_target_value_low=1150, custom_target_value_high=1150, intensity="rest"),
    dict(duration_type="repeat_until_steps_cmplt", duration_value=1, target_type="open", target_value=2),
    dict(wkt_step_name="Cool down", duration_type="time", duration_value=300_000, target_type="open",
         intensity="cooldown"),
]

# FIT workout_hr: > 100 bpm + 100, 1..100 percent of the rider's maximum heart rate
HEART_RATE_ERG = [
    dict(wkt_step_name="Warm up", duration_type="time", duration_value=300_000, target_type="power", target_value=0,
         custom_target_value_low=1120, custom_target_value_high=1120, intensity="warmup"),
    dict(wkt_step_name="Zone 2", duration_type="time", duration_value=1_200_000, target_type="heart_rate",
         target_value=0, custom_target_value_low=230, custom_target_value_high=240, intensity="active",
         secondary_target_type="cadence", secondary_custom_target_value_low=85,
         secondary_custom_target_value_high=95),
    dict(wkt_step_name="Tempo", duration_type="time", duration_value=600_000, target_type="heart_rate",
         target_value=0, custom_target_value_low=80, custom_target_value_high=84, intensity="active"),
    dict(wkt_step_name="Cool down", duration_type="time", duration_value=300_000, target_type="open",
         intensity="cooldown"),
]


def heart_rate_step(seconds: float, lo: int, hi: int | None = None, **extra) -> dict:
    """A time step with a custom heart-rate range (FIT workout_hr values: bpm + 100 or % of max)."""
    return dict(duration_type="time", duration_value=int(seconds * 1000), target_type="heart_rate", target_value=0,
                custom_target_value_low=lo, custom_target_value_high=lo if hi is None else hi, **extra)


def fit_workout_bytes(steps: list[dict], *, name: str = "Test workout", sport: str = "cycling",
                      file_type: str = "workout", with_index: bool = True) -> bytes:
    """A FIT workout file: file_id, workout, one workout_step per dict (FIT SDK field names)."""
    from garmin_fit_sdk import Encoder, Profile

    mesg_num = Profile["mesg_num"]
    enc = Encoder()
    enc.write_mesg({"mesg_num": mesg_num["FILE_ID"], "type": file_type, "manufacturer": "development", "product": 0,
                    "serial_number": 1234,
                    "time_created": datetime.datetime(2026, 12, 5, tzinfo=datetime.timezone.utc)})
    enc.write_mesg({"mesg_num": mesg_num["WORKOUT"], "sport": sport, "num_valid_steps": len(steps), "wkt_name": name})
    for i, step in enumerate(steps):
        mesg = {"mesg_num": mesg_num["WORKOUT_STEP"], **step}
        if with_index:
            mesg.setdefault("message_index", i)
        enc.write_mesg(mesg)
    return enc.close()


if __name__ == "__main__":
    out = pathlib.Path(__file__).resolve().parent / "data" / "workouts" / "sweet_spot.fit"
    out.write_bytes(fit_workout_bytes(SWEET_SPOT, name="Sweet spot 2x8"))
    print(f"wrote {out} ({out.stat().st_size} bytes)")
