"""CAN side of the bike plant: drive protocols (no ROS imports) and the plant's CAN backend.

* :mod:`bike_plant.can.protocol` -- :class:`DriveProtocol` (abstract host side of a drive
  on a python-can bus) and :class:`OdriveCanSimple` (ODrive CANSimple, firmware 0.6.x,
  over the DBC ``odrive_cansimple_0_6.dbc`` shipped in this folder, node 0 ids) and
  :class:`VescCan` (VESC CAN mode "VESC", over ``vesc_can.dbc``, VESC ID 0 ids).
* the drive emulator (``bike-drive-emulator``, an ODrive-like drive whose physics is the bike
  of a config file) is :mod:`bike_controller.drive_emulator`: its firmware runs the
  controller package's current loops, and bike_plant depends on no other package of ours.

Names are imported lazily (PEP 562): ``import bike_plant.can`` stays light, and
``python -m bike_plant.can.protocol`` does not find its module imported twice.
"""
from __future__ import annotations

import importlib

_PROTOCOL_NAMES = (
    "DBC_PATH", "DRIVE_TO_HOST", "HOST_TO_DRIVE", "IGNORED_REASONS", "MALFORMED_REASONS", "MEASUREMENT_KINDS",
    "AxisState", "ControlMode", "DriveProtocol", "InputMode", "Measurement", "ODriveError", "OdriveCanSimple",
    "OdriveCanSimpleCodec", "PROTOCOLS", "ProcedureResult", "error_names", "export_dbc", "load_database",
    "DbcCodec", "VESC_DBC_PATH", "VESC_DRIVE_TO_HOST", "VESC_HOST_TO_DRIVE", "VescCan", "VescCanCodec",
)

__all__ = list(_PROTOCOL_NAMES)


def __getattr__(name: str):
    if name in _PROTOCOL_NAMES:
        return getattr(importlib.import_module(".protocol", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_PROTOCOL_NAMES))
