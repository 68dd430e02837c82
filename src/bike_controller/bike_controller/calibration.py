"""Spin-down calibration kept between runs, as a trainer keeps it in its memory (no rclpy).

A smart trainer stores the friction its last spin-down found and rides with it after every
power-up until the next spin-down (research notes, trainers.md section 5: apps ask for one
now and then, not at every ride). Here:

- the controller node writes the figures into its ``calibration_file`` the moment a spin-down
  succeeds (:func:`write_calibration`: one small YAML file, replaced atomically, so a run
  killed while writing leaves the previous calibration whole);
- ``./bike run --calibration FILE`` rides with them: :func:`read_calibration` checks the file
  and :func:`apply_calibration` puts the figures into the run's config as
  ``modes.friction_nms`` / ``modes.dry_friction_nm`` (bike_controller.modes.friction_figures:
  what the mode laws take the friction from). The recorded config therefore carries them, and
  the report and ``./bike replay`` ride the same bike without the file.

The plant's true friction (``mechanics.friction_nms``, ``spmsm.dry_friction_nm``) is never
touched: the calibration is the trainer's belief about it.
"""
from __future__ import annotations

import datetime
import os
import pathlib
import tempfile
from dataclasses import dataclass

from bike_plant.config import YamlFileError, dump_ros_params, read_yaml_file
from bike_plant.params import friction_problem

MAX_CALIBRATION_BYTES = 64 * 1024   # the file is a few hundred bytes; refuse anything absurd unparsed
FIGURES = ("friction_nms", "dry_friction_nm")
HEADER = ("# Spin-down calibration of a bike, written by its controller when a spin-down succeeded\n"
          "# (bike_controller.calibration). `./bike run --calibration FILE` rides with these figures.\n")


class CalibrationError(ValueError):
    """A calibration file that cannot be used, with its path."""

    def __init__(self, message: str, path):
        super().__init__(f"calibration {path}: {message}")


@dataclass(frozen=True)
class Calibration:
    machine: str                  # bldc | spmsm: a calibration belongs to one machine
    friction_nms: float           # viscous B [N m s/rad], motor shaft
    dry_friction_nm: float        # Coulomb Tc [N m], motor shaft
    written_utc: str = ""         # when the spin-down succeeded (wall clock), for the user
    coast_s: float = 0.0          # the fitted coast, for the user

    def describe(self) -> str:
        when = f" of {self.written_utc}" if self.written_utc else ""
        return (f"B {self.friction_nms:.4g} N m s, Tc {self.dry_friction_nm:.4g} N m (the spin-down{when}, "
                f"{self.coast_s:.1f} s coast)")


def write_calibration(path, machine: str, result, *, sim_time_s: float, config_path: str = "") -> pathlib.Path:
    """Store a spin-down's result (bike_controller.spindown.SpinDownResult) in ``path``: written
    beside it and renamed over it, so a reader sees the old file or the new one, never half of
    one. OSError when it cannot be written or ``path`` is no regular file (the rename would
    replace a device or pipe, e.g. /dev/null, with the calibration)."""
    path = pathlib.Path(path)
    if path.exists() and not path.is_file():
        raise OSError(f"{path}: not a regular file, and a calibration replaces the file it is written to")
    doc = {"machine": machine,
           "written_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "sim_time_s": round(float(sim_time_s), 6),
           "config": str(config_path),
           "coast_s": round(float(result.coast_s), 3),
           "samples": int(result.samples),
           "rms_residual_rpm": float(result.rms_residual_rpm),
           "modes": {"friction_nms": float(result.friction_nms), "dry_friction_nm": float(result.dry_friction_nm)}}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(HEADER + dump_ros_params(doc, sort_keys=False))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_calibration(path, machine: str) -> Calibration:
    """The calibration in ``path`` for a bike of kind ``machine``; CalibrationError naming the
    problem when the file is unreadable, not one this module wrote, another machine's, or
    carries a figure outside bike_plant.params.friction_problem's range."""
    path = pathlib.Path(path)
    try:
        doc = read_yaml_file(path, MAX_CALIBRATION_BYTES)
    except YamlFileError as exc:
        raise CalibrationError(str(exc), path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("modes"), dict):
        raise CalibrationError("expected a mapping with a 'modes:' mapping of friction_nms and dry_friction_nm "
                               "(a file the controller wrote after a spin-down)", path)
    if "machine" not in doc:
        # it said "a None bike's calibration"
        raise CalibrationError(f"no 'machine:' key: the controller writes the bike's kind (bldc or spmsm) "
                               f"with its spin-down, and this bike is {machine!r}", path)
    if doc.get("machine") != machine:
        raise CalibrationError(f"it is a {doc.get('machine')!r} bike's calibration, and this bike is {machine!r}", path)
    modes = doc["modes"]
    unknown = sorted(str(k) for k in set(modes) - set(FIGURES))
    if unknown:
        raise CalibrationError(f"modes: unknown key(s) {', '.join(unknown)}", path)
    figures = {}
    for key in FIGURES:
        v = modes.get(key)
        problem = friction_problem(key, v)
        if problem:
            raise CalibrationError(f"modes.{problem}", path)
        figures[key] = float(v)
    coast = doc.get("coast_s", 0.0)
    coast = float(coast) if isinstance(coast, (int, float)) and not isinstance(coast, bool) else 0.0
    return Calibration(machine, figures["friction_nms"], figures["dry_friction_nm"],
                       str(doc.get("written_utc") or ""), coast)


def apply_calibration(doc: dict, calibration: Calibration) -> dict:
    """The parameter file ``doc`` with the calibration as every section's
    ``modes.friction_nms`` / ``dry_friction_nm`` (a node's own section would otherwise win over
    the wildcard's). ``doc`` is modified and returned."""
    figures = {"friction_nms": calibration.friction_nms, "dry_friction_nm": calibration.dry_friction_nm}
    for name, body in doc.items():
        params = body.get("ros__parameters") if isinstance(body, dict) else None
        if not isinstance(params, dict):
            continue
        modes = params.get("modes")
        if name == "/**" and modes is None:
            params["modes"] = dict(figures)
        elif isinstance(modes, dict) and (name == "/**" or any(k in modes for k in FIGURES)):
            modes.update(figures)          # (a modes: that is no mapping is the config check's to name)
    return doc
