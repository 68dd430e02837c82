"""bike_plant.cdr: the loop's hot messages as bytes. Checked against rclpy's own
serialization both ways, on random messages (every field, sequences empty and not, strings
with multi-byte characters) and on the plant's real snapshots; malformed bytes give
CdrError, never another exception or a read past the end."""
from __future__ import annotations

import random
import struct

import numpy as np
import pytest

pytest.importorskip("rclpy")

from bike_msgs.msg import ControllerStatus, DriveCommand, PlantState  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from bike_plant import msgconv  # noqa: E402
from bike_plant.cdr import CdrError, Codec  # noqa: E402

_INT_RANGE = {"uint8": (0, 255), "int8": (-128, 127), "uint16": (0, 65535), "int16": (-32768, 32767),
              "uint32": (0, 2**32 - 1), "int32": (-2**31, 2**31 - 1), "uint64": (0, 2**64 - 1),
              "int64": (-2**63, 2**63 - 1), "octet": (0, 255)}


def _random_value(rng: random.Random, ftype: str):
    if ftype == "boolean":
        return rng.random() < 0.5
    if ftype in _INT_RANGE:
        return rng.randint(*_INT_RANGE[ftype])
    if ftype == "double":
        return rng.uniform(-1e6, 1e6)
    if ftype == "float":
        return float(np.float32(rng.uniform(-1e3, 1e3)))
    if ftype == "string":
        return "".join(rng.choice("abcé€ 1_/") for _ in range(rng.randint(0, 9)))
    if ftype.startswith("sequence<"):
        base = ftype[9:-1]
        return [_random_value(rng, base) for _ in range(rng.choice([0, 0, 1, 2, 3, 7, 60]))]
    base, count = ftype[:-1].split("[")
    return [_random_value(rng, base) for _ in range(int(count))]


def _random_msg(cls, rng: random.Random):
    msg = cls()
    for name, ftype in cls.get_fields_and_field_types().items():
        if name == "header":
            msg.header.stamp.sec = rng.randint(0, 2**31 - 1)
            msg.header.stamp.nanosec = rng.randint(0, 999_999_999)
            msg.header.frame_id = _random_value(rng, "string")
        else:
            setattr(msg, name, _random_value(rng, ftype))
    return msg


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple, np.ndarray)) or hasattr(a, "tolist"):
        return list(np.asarray(a).tolist()) == list(np.asarray(b).tolist())
    return a == b and type(a) is type(b)


@pytest.mark.parametrize("cls", [PlantState, DriveCommand, ControllerStatus])
def test_random_messages_both_ways_against_rclpy(cls):
    codec = Codec(cls)
    rng = random.Random(7)
    for _ in range(300):
        msg = _random_msg(cls, rng)
        raw = serialize_message(msg)
        sec, nanosec, frame_id, values = codec.decode(raw)
        assert (sec, nanosec, frame_id) == (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
        for name in cls.get_fields_and_field_types():
            if name != "header":
                assert _same(getattr(msg, name), values[name]), name
        mine = codec.encode(values, sec, nanosec, frame_id)
        assert deserialize_message(mine, cls) == msg
        assert len(mine) == len(raw)
        assert codec.encode(values, sec, nanosec, frame_id) == mine, "same values, same bytes"


def test_pad_bytes_are_zero_and_missing_fields_are_defaults():
    codec = Codec(PlantState)
    raw = codec.encode({}, 0, 0, "")
    assert deserialize_message(raw, PlantState) == PlantState()
    assert set(raw[4:]) <= {0, 1}            # only the strings' length words (1: the NUL) are non-zero
    raw = codec.encode({"hall_state": 1, "seq": 2})           # uint8 then uint64 later: padding between
    msg = deserialize_message(raw, PlantState)
    assert (msg.hall_state, msg.seq) == (1, 2)


def test_the_plant_snapshots_encode_like_the_message_path():
    from bike_plant.config import load_config
    from bike_plant.node import SimBackend, SpmsmSimBackend

    for config, backend in (("config/bldc_default.yaml", SimBackend), ("config/spmsm_default.yaml", SpmsmSimBackend)):
        be = backend(load_config(msgconv_root() / config), 0)
        snap = be.snapshot()
        snap.update(seq=12, batch_periods=20, backend="sim", measured_by_drive=False, end_of_run=False)
        stamp = 1_234_567_890_123
        via_msg = msgconv.plant_state_msg(snap, stamp)
        raw = msgconv.plant_state_cdr(snap, stamp)
        assert deserialize_message(raw, PlantState) == via_msg, config
        view = msgconv.PlantStateView(serialize_message(via_msg))
        assert view.stamp_ns == stamp and view.seq == 12 and view.batch_periods == 20
        old = msgconv.snapshot_from_msg(via_msg)
        assert old.keys() == view.snap.keys()
        assert all(_same(old[k], view.snap[k]) for k in old)


def test_drive_commands_encode_like_the_message_path():
    rng = np.random.default_rng(3)
    n = 20
    ga, gb = rng.integers(0, 64, n).astype(np.uint8), rng.integers(0, 64, n).astype(np.uint8)
    split = rng.random(n)
    raw = msgconv.drive_command_cdr(5, ga, gb, split, 7_000_000_123, 1.5, -2.25)
    assert deserialize_message(raw, DriveCommand) == msgconv.drive_command_msg(5, ga, gb, split, 7_000_000_123,
                                                                              1.5, -2.25)
    view = msgconv.DriveCommandView(raw)
    assert view.seq == 5 and view.stamp_ns == 7_000_000_123 and view.current_cmd_a == -2.25
    assert msgconv.drive_command_problem(view, n) is None
    a, b, s = msgconv.drive_arrays(view)
    assert np.array_equal(a, ga) and np.array_equal(b, gb) and np.array_equal(s, split.astype(np.float32))
    duties = rng.random((n, 3))
    raw = msgconv.spmsm_drive_cdr(6, duties, np.ones(n), rng.random(n), 9, 0.5, 0.25)
    assert deserialize_message(raw, DriveCommand) == msgconv.spmsm_drive_msg(6, duties, np.ones(n),
                                                                            np.frombuffer(msgconv.DriveCommandView(
                                                                                raw).buck_duty, np.float32), 9,
                                                                            0.5, 0.25)
    assert msgconv.spmsm_drive_problem(msgconv.DriveCommandView(raw), n) is None
    # the checks still refuse a bad batch read from bytes
    bad = msgconv.DriveCommandView(msgconv.drive_command_cdr(5, ga, gb, np.full(n, np.nan), 0))
    assert "non-finite" in msgconv.drive_command_problem(bad, n)


def test_clock_encodes_like_the_message_path():
    from rosgraph_msgs.msg import Clock

    for stamp in (0, 1, 999_999_999, 1_000_000_000, 3_600_123_456_789, 2**31 * 1_000_000_000 - 1):
        raw = msgconv.clock_cdr(stamp)
        assert raw == serialize_message(Clock(clock=msgconv.time_msg(stamp)))
        assert msgconv.stamp_ns(deserialize_message(raw, Clock).clock) == stamp


def test_the_plant_applies_checked_read_only_arrays_like_validated_ones():
    """The node's path hands the kernel read-only views of the DriveCommand's bytes (after
    drive_command_problem); the result is the validated path's, in the safe state too."""
    from bike_plant.config import load_config
    from bike_plant.params import plant_params_from_config
    from bike_plant.sim import BldcPlant

    rng = np.random.default_rng(5)
    n = 40
    plants = [BldcPlant(plant_params_from_config(load_config(None)), seed=1) for _ in range(2)]
    for batch in range(6):
        ga, gb = rng.integers(0, 64, n).astype(np.uint8), rng.integers(0, 64, n).astype(np.uint8)
        view = msgconv.DriveCommandView(msgconv.drive_command_cdr(batch, ga, gb, rng.random(n), 0))
        assert msgconv.drive_command_problem(view, n) is None
        arrays = msgconv.drive_arrays(view)
        assert not arrays[0].flags.writeable
        for plant in plants:
            if batch == 3:
                plant.set_safe_state()
        plants[0].step_batch(*arrays)
        plants[1].step_batch(*arrays, checked=True)
        assert np.array_equal(plants[0].state, plants[1].state)
    assert np.array_equal(np.frombuffer(view.gates_a, np.uint8), ga), "the message's bytes stay as sent"


def test_the_spmsm_plant_applies_checked_arrays_like_validated_ones_and_the_check_words_each_problem():
    """The SPMSM node's path: spmsm_drive_problem's compiled check, then the message's float64
    conversions applied without a second validation and kept (SpmsmPlant.step_batch(checked=True));
    the state is the validated path's, held and safe batches after it too. A bad array is
    refused with the words the numpy check gave."""
    from bike_plant import spmsm as M
    from bike_plant.config import load_config

    cfg = load_config(msgconv_root() / "config" / "spmsm_default.yaml")
    rng = np.random.default_rng(7)
    n = 10
    plants = [M.SpmsmPlant(M.plant_params_from_config(cfg)) for _ in range(2)]
    for batch in range(8):
        relay = (rng.random(n) > 0.7).astype(np.float32)
        view = msgconv.DriveCommandView(msgconv.spmsm_drive_cdr(batch, rng.random((n, 3)), relay, rng.random(n), 0))
        assert msgconv.spmsm_drive_problem(view, n) is None
        plants[0].step_batch(*msgconv.spmsm_drive_arrays(view))
        plants[1].step_batch(*msgconv.spmsm_drive_arrays(view), checked=True)
        assert plants[1].last_inputs[0].flags.writeable, "kept: a conversion, not a view of the message"
        for plant in plants:
            if batch == 5:
                plant.step_held_batch()
            if batch == 6:
                plant.set_safe_state()
                plant.step_safe_batch(n)
                plant.clear_safe_state()
        assert np.array_equal(plants[0].state, plants[1].state)
    for k, name in enumerate(("duty_abc", "relay_request", "buck_duty")):
        for value, words in ((np.nan, "holds a non-finite value"), (-np.inf, "holds a non-finite value"),
                             (-0.25, "outside [0, 1] (-0.25 .. "), (1.5, "outside [0, 1] (")):
            arrays = [np.full(3 * n, 0.5, np.float32), np.zeros(n, np.float32), np.ones(n, np.float32)]
            arrays[k][-1] = value
            problem = msgconv.spmsm_drive_problem(msgconv.DriveCommandView(msgconv.spmsm_drive_cdr(0, *arrays, 0)), n)
            assert problem.startswith(f"{name} {words}"), (name, value, problem)


def test_controller_status_encodes_like_the_message_path():
    status = {"seq": 9, "command": 0.5, "mode": 2, "command_rejected": False, "speed_est_rpm": np.float64(812.5),
              "region": np.float64(1.0), "quadrant": 1, "family": "predictive", "not_a_field": object(),
              "iq_a": np.float32(3.25)}
    raw = msgconv.controller_status_cdr(status, 3_500_000_000)
    assert deserialize_message(raw, ControllerStatus) == msgconv.controller_status_msg(status, 3_500_000_000)


def test_malformed_bytes_give_cdr_error_only():
    codec = Codec(PlantState)
    msg = _random_msg(PlantState, random.Random(1))
    msg.current_samples_a = [1.0] * 60
    raw = serialize_message(msg)
    for cut in range(len(raw)):                         # every truncation
        with pytest.raises(CdrError):
            codec.decode(raw[:cut])
    with pytest.raises(CdrError):
        codec.decode(b"\x01\x01\x00\x00" + raw[4:])     # big-endian / unknown encapsulation
    # a sequence that claims 2^32-1 elements: refused, nothing allocated. DriveCommand with an
    # empty frame_id: sec, nanosec, length 1, NUL + 3 pad, seq (8-aligned), then gates_a's count
    drive = msgconv.drive_command_cdr(1, np.zeros(3, np.uint8), np.zeros(3, np.uint8), np.zeros(3), 0)
    assert struct.unpack_from("<I", drive, 4 + 24)[0] == 3
    hostile = bytearray(drive)
    struct.pack_into("<I", hostile, 4 + 24, 2**32 - 1)
    with pytest.raises(CdrError, match="gates_a claims"):
        msgconv.DriveCommandView(bytes(hostile))
    rng = random.Random(5)
    for _ in range(2000):                               # random corruption: CdrError or a value, nothing else
        hostile = bytearray(raw)
        for _ in range(rng.randint(1, 6)):
            hostile[rng.randrange(4, len(hostile))] = rng.randrange(256)
        try:
            codec.decode(bytes(hostile))
        except CdrError:
            pass
    with pytest.raises(CdrError):
        codec.encode({"hall_state": 300})              # does not fit uint8
    with pytest.raises(CdrError):
        msgconv.DriveCommandView(b"\x00\x01\x00\x00\xff\xff")


def msgconv_root():
    import pathlib
    return pathlib.Path(__file__).resolve().parents[1]


def test_a_bad_rider_cadence_is_a_problem_of_the_drive_command_and_of_the_command():
    import numpy as np
    n = 4
    for build, problem in ((msgconv.drive_command_cdr, msgconv.drive_command_problem),
                           (msgconv.spmsm_drive_cdr, msgconv.spmsm_drive_problem)):
        arrays = ((np.zeros(n, np.uint8), np.zeros(n, np.uint8), np.zeros(n, np.float32))
                  if build is msgconv.drive_command_cdr else
                  (np.full(3 * n, 0.5, np.float32), np.zeros(n, np.float32), np.zeros(n, np.float32)))
        good = msgconv.DriveCommandView(build(0, *arrays, 0, 0.0, 0.0, 95.0))
        assert good.rider_cadence_rpm == 95.0 and problem(good, n) is None
        for bad in (float("nan"), -5.0, 5.0, 300.0):
            view = msgconv.DriveCommandView(build(0, *arrays, 0, 0.0, 0.0, bad))
            assert "rider_cadence_rpm" in problem(view, n), bad
    assert msgconv.command_problem(msgconv.command_msg(0.5, 2, cadence_rpm=95.0)) is None
    assert "cadence target" in msgconv.command_problem(msgconv.command_msg(0.5, 2, cadence_rpm=400.0))
