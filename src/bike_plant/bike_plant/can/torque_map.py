"""Torque map of a drive on CAN: the shaft's true torque against what the drive reports.

A drive's torque estimate is kt x its measured current. For a sinusoidal machine under field
oriented control that is the torque to within a fraction of a percent; for the BLDC of paper
000 it is not: the commutation dips and the (|ia| + |ib| + |ic|) / 2 current feedback
(section 4.3) make the true mean torque smaller than kt I by a share that grows with the
current (braking at 2600-2800 r/min: -1 % at 0.5 N m .. +11 % at 2.6 N m, measured on the
drive emulator's physics). A trainer that reports kt I overstates the rider's power by that,
and a brake asked for T delivers less. The same correction the paper makes with its factor k
(Eq. 7: the torque per ampere it measured), here measured on the drive and its motor.

The map is measured at fixed speeds (a dynamometer or prime mover holds the shaft) for a grid
of torque setpoints: per speed and setpoint the drive's mean reported torque (Torque_Estimate,
kt Iq) and the shaft's mean true torque (a torque sensor; on the emulator the physics' own
electromagnetic torque). ``./bike torque-map`` measures it on the emulated drive; on hardware a
dynamometer with a torque sensor fills the same file. The plant's CAN backend
(``can.torque_map_file``) then

- reports ``true_nm(speed, reported)`` as the PlantState's torque (the trainer's power, the
  plant's ledger, the controller's torque trim), and
- sends ``setpoint_nm(speed, wanted)`` for a wanted shaft torque (the brake the controller asks
  for is the brake the rider feels).

Both interpolate linearly in speed between the rows and, within the row, between setpoints.
Outside the measured speeds the nearest row holds; beyond a row's largest |torque| its last
ratio true / reported holds (torque proportional to current). Both cases are counted
(:attr:`TorqueMap.outside`), and the plant's CAN diagnostic says so: a map that does not
cover the ride is visible, not silently clamped.

File format (YAML, read with ``yaml.safe_load``; every list a flat list of numbers, rows of
``speed_rpm`` one after the other)::

    drive_torque_map:
      source: "free text: how it was measured"
      speed_rpm: [1500.0, 2000.0, ...]          # ascending, at least 1
      setpoint_nm: [-2.9, ..., 0.0, ..., 2.9]   # ascending, at least 2, 0 among them
      reported_nm: [...]       # len(speed_rpm) x len(setpoint_nm): the drive's Torque_Estimate
      true_nm: [...]           # the same shape: the shaft's torque (torque sensor)

Within each row ``reported_nm`` and ``true_nm`` must rise with the setpoint (an inverse must
exist) and keep its sign (no brake where motoring is asked).
"""
from __future__ import annotations

import dataclasses
import math
import os
import pathlib

import numpy as np

from ..config import YamlFileError, dump_ros_params, read_yaml_file

MAP_KEY = "drive_torque_map"
# in the ``source`` of a map measured on bike-drive-emulator's physics (./bike torque-map): a real
# drive with such a map gets the emulated machine's corrections, which the plant warns about
EMULATED_SOURCE_MARK = "the drive emulator's plant physics"
MAX_MAP_BYTES = 1 << 20          # a map is a few kB; refuse anything absurd before parsing
MAX_POINTS = 100_000


class TorqueMapError(ValueError):
    """A torque map that cannot be used, with the file it came from."""

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        super().__init__(f"{path or '<torque map>'}: {message}")
        self.path = path


@dataclasses.dataclass
class TorqueMap:
    """Measured (speed, setpoint) grid of the drive's reported and the shaft's true torque."""
    speed_rpm: np.ndarray            # (n,) ascending
    setpoint_nm: np.ndarray          # (m,) ascending, 0 among them
    reported_nm: np.ndarray          # (n, m)
    true_nm: np.ndarray              # (n, m)
    source: str = ""
    path: str = ""
    outside: int = 0                 # lookups outside the measured grid (nearest row / last ratio held)

    def __post_init__(self):
        self.speed_rpm = np.asarray(self.speed_rpm, dtype=float)
        self.setpoint_nm = np.asarray(self.setpoint_nm, dtype=float)
        n, m = self.speed_rpm.size, self.setpoint_nm.size
        try:
            self.reported_nm = np.asarray(self.reported_nm, dtype=float).reshape(n, m)
            self.true_nm = np.asarray(self.true_nm, dtype=float).reshape(n, m)
        except ValueError:
            raise TorqueMapError(f"reported_nm and true_nm need len(speed_rpm) x len(setpoint_nm) = {n} x {m} "
                                 f"= {n * m} values, got {np.size(self.reported_nm)} and {np.size(self.true_nm)}",
                                 self.path or None) from None
        self._check()

    # ------------------------------------------------------------------ validation
    def _check(self) -> None:
        def fail(text: str):
            raise TorqueMapError(text, self.path or None)

        n, m = self.speed_rpm.size, self.setpoint_nm.size
        if n < 1 or m < 2:
            fail(f"needs at least 1 speed and 2 setpoints, got {n} and {m}")
        if n * m > MAX_POINTS:
            fail(f"{n * m} points, more than {MAX_POINTS}")
        for name in ("speed_rpm", "setpoint_nm", "reported_nm", "true_nm"):
            if not np.all(np.isfinite(getattr(self, name))):
                fail(f"{name} has a value that is not a finite number")
        if np.any(np.diff(self.speed_rpm) <= 0):
            fail(f"speed_rpm must be strictly ascending, got {self.speed_rpm.tolist()}")
        if np.any(np.diff(self.setpoint_nm) <= 0):
            fail(f"setpoint_nm must be strictly ascending, got {self.setpoint_nm.tolist()}")
        if not np.any(self.setpoint_nm == 0.0):
            fail("setpoint_nm must contain 0 (no torque asked, none reported)")
        for i, speed in enumerate(self.speed_rpm):
            for name in ("reported_nm", "true_nm"):
                row = getattr(self, name)[i]
                if np.any(np.diff(row) <= 0):
                    fail(f"{name} at {speed:g} rpm does not rise with the setpoint ({_short(row)}): "
                         "no inverse (re-measure that speed, or leave it out)")
                if np.any(row * self.setpoint_nm < 0):
                    fail(f"{name} at {speed:g} rpm has the opposite sign of its setpoint ({_short(row)})")

    # ------------------------------------------------------------------ lookups
    def _rows(self, speed_rpm: float) -> tuple[np.ndarray, np.ndarray]:
        """(reported, true) rows at ``speed_rpm``, linear between the measured speeds."""
        s = self.speed_rpm
        if not (s[0] <= speed_rpm <= s[-1]):
            self.outside += 1
        if s.size == 1 or speed_rpm <= s[0]:
            return self.reported_nm[0], self.true_nm[0]
        if speed_rpm >= s[-1]:
            return self.reported_nm[-1], self.true_nm[-1]
        j = int(np.searchsorted(s, speed_rpm, side="right")) - 1
        f = (speed_rpm - s[j]) / (s[j + 1] - s[j])
        return ((1.0 - f) * self.reported_nm[j] + f * self.reported_nm[j + 1],
                (1.0 - f) * self.true_nm[j] + f * self.true_nm[j + 1])

    def _along(self, x: float, xs: np.ndarray, ys: np.ndarray) -> float:
        """y(x) on a rising row through (0, 0); beyond its ends the end's ratio y / x holds."""
        if x > xs[-1]:
            self.outside += 1
            return x * ys[-1] / xs[-1] if xs[-1] > 0 else float(ys[-1])
        if x < xs[0]:
            self.outside += 1
            return x * ys[0] / xs[0] if xs[0] < 0 else float(ys[0])
        return float(np.interp(x, xs, ys))

    def true_nm_at(self, speed_rpm: float, reported_nm: float) -> float:
        """The shaft's torque for the drive's reported torque at ``speed_rpm``."""
        if not (math.isfinite(speed_rpm) and math.isfinite(reported_nm)):
            return reported_nm
        rep, true = self._rows(abs(speed_rpm))
        return self._along(reported_nm, rep, true)

    def setpoint_nm_for(self, speed_rpm: float, wanted_nm: float) -> float:
        """The torque setpoint that gives the shaft ``wanted_nm`` at ``speed_rpm``."""
        if not (math.isfinite(speed_rpm) and math.isfinite(wanted_nm)):
            return wanted_nm
        _, true = self._rows(abs(speed_rpm))
        return self._along(wanted_nm, true, self.setpoint_nm)

    def describe(self) -> str:
        return (f"torque map {self.path or '(in memory)'}: {self.speed_rpm.size} speeds "
                f"{self.speed_rpm[0]:g}-{self.speed_rpm[-1]:g} rpm x {self.setpoint_nm.size} setpoints "
                f"{self.setpoint_nm[0]:g}..{self.setpoint_nm[-1]:g} N m")

    # ------------------------------------------------------------------ files
    def to_yaml(self) -> str:
        body = {"source": self.source, "speed_rpm": _floats(self.speed_rpm), "setpoint_nm": _floats(self.setpoint_nm),
                "reported_nm": _floats(self.reported_nm), "true_nm": _floats(self.true_nm)}
        head = ("# Drive torque map (bike_plant.can.torque_map): per speed_rpm row, the drive's reported\n"
                "# torque (kt Iq) and the shaft's true torque at each torque setpoint; rows one after the other.\n")
        # numbers and text as load_torque_map and ROS 2's parameter parser both read them back
        return head + dump_ros_params({MAP_KEY: body}, sort_keys=False, width=100, default_flow_style=None)

    def save(self, path: str | os.PathLike) -> None:
        """Write atomically (a reader never sees half a map)."""
        path = pathlib.Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(self.to_yaml())
        os.replace(tmp, path)


def load_torque_map(path: str | os.PathLike) -> TorqueMap:
    """Read a map file; TorqueMapError (one message naming the file) on any problem."""
    path = pathlib.Path(path)
    try:
        doc = read_yaml_file(path, MAX_MAP_BYTES)
    except YamlFileError as exc:
        raise TorqueMapError(str(exc), path) from None
    body = doc.get(MAP_KEY) if isinstance(doc, dict) else None
    if not isinstance(body, dict):
        raise TorqueMapError(f"expected a mapping '{MAP_KEY}:' at the top", path)
    values = {}
    for key in ("speed_rpm", "setpoint_nm", "reported_nm", "true_nm"):
        v = body.get(key)
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise TorqueMapError(f"{MAP_KEY}.{key} must be a flat list of numbers", path)
        values[key] = v
    source = body.get("source", "")
    return TorqueMap(**values, source=str(source), path=str(path))


CSV_COLUMNS = ("speed_rpm", "setpoint_nm", "reported_nm", "true_nm")
MAX_CSV_BYTES = 16 << 20        # a dynamometer log of points, not a raw trace


def torque_map_from_csv(path: str | os.PathLike) -> TorqueMap:
    """A map from a dynamometer's points: a CSV file with the header ``speed_rpm, setpoint_nm,
    reported_nm, true_nm`` (more columns are ignored) and one row per measured point (the drive's
    mean Torque_Estimate and the torque sensor's mean at a held speed and a torque setpoint).
    Repeated points are averaged; every speed needs every setpoint (0 included: measure it, a
    drive at rest reports its offset). TorqueMapError with one reason (and the line) otherwise."""
    import csv

    path = pathlib.Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_CSV_BYTES:
            raise TorqueMapError(f"file too large ({size} bytes > {MAX_CSV_BYTES})", path)
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh, skipinitialspace=True)
            missing = [c for c in CSV_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise TorqueMapError(f"needs the columns {', '.join(CSV_COLUMNS)}; missing {', '.join(missing)}", path)
            points: dict[tuple[float, float], list[tuple[float, float]]] = {}
            for row in reader:
                try:
                    speed, setpoint, reported, true = (float(row[c]) for c in CSV_COLUMNS)
                except (TypeError, ValueError):
                    raise TorqueMapError(f"line {reader.line_num}: not four numbers "
                                         f"({', '.join(str(row.get(c)) for c in CSV_COLUMNS)})", path) from None
                if not all(math.isfinite(x) for x in (speed, setpoint, reported, true)):
                    raise TorqueMapError(f"line {reader.line_num}: a value that is not finite", path)
                points.setdefault((speed, setpoint), []).append((reported, true))
    except TorqueMapError:
        raise
    except OSError as exc:
        raise TorqueMapError(f"cannot read it ({exc.strerror or exc})", path) from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise TorqueMapError(f"not a CSV text file ({exc})", path) from None
    if not points:
        raise TorqueMapError("no points", path)
    speeds = sorted({k[0] for k in points})
    setpoints = sorted({k[1] for k in points})
    gaps = [(s, t) for s in speeds for t in setpoints if (s, t) not in points]
    if gaps:
        shown = ", ".join(f"{t:g} N m at {s:g} rpm" for s, t in gaps[:5]) + (", ..." if len(gaps) > 5 else "")
        raise TorqueMapError(f"every speed needs every setpoint; {len(gaps)} missing: {shown}", path)
    mean = {k: np.mean(np.array(v), axis=0) for k, v in points.items()}
    reported = [[mean[(s, t)][0] for t in setpoints] for s in speeds]
    true = [[mean[(s, t)][1] for t in setpoints] for s in speeds]
    n_rows = sum(len(v) for v in points.values())
    return TorqueMap(speeds, setpoints, reported, true, path=str(path),
                     source=f"dynamometer points of {path.name} ({n_rows} rows, repeated points averaged)")


def _floats(a: np.ndarray) -> list[float]:
    return [float(f"{x:.6g}") for x in np.ravel(a)]


def _short(row: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in row[:12]) + (", ..." if row.size > 12 else "") + "]"
