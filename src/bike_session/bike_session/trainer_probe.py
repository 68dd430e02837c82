"""`./bike trainer`: the app's end of FTMS over DIRCON, for a quick look at a trainer on the
network, this testbed's (`./bike run --ftms`) or a real one (a KICKR, a Neo, a SmartSpin2k):
find trainers by mDNS, list a trainer's services, characteristics, FTMS ranges and training
status, optionally take control and set a target, and print the Indoor Bike Data it notifies,
once a second (and its Training Status when it changes).

    ./bike trainer --find                         # trainers announced on the network (3 s)
    ./bike trainer [--host H] [--port P]          # what the trainer at H:P serves, then 5 s of data
    ./bike trainer --power 200 --seconds 30       # ERG at 200 W (Request Control first)
    ./bike trainer --grade 4.5                    # simulation grade 4.5 % (road: --crr, --cw, --wind)
    ./bike trainer --grade -10 --difficulty 50    # as Zwift sends it at trainer difficulty 50 %: -2.5 %
    ./bike trainer --power 200 --cadence 95       # ... and the rider's cadence target (Set Targeted Cadence)
    ./bike trainer --workout FILE.zwo --ftp 250 --csv ride.csv   # ride a workout on the trainer
    ./bike trainer --spindown                     # its spin-down calibration (Spin Down Control)

``--workout`` rides a workout file (.zwo, .erg, .mrc, .fit, or a profile .yaml) on the trainer
the way an app does: its targets, mapped through the trainer's own ranges (power, inclination,
resistance level), are written to the Control Point when they change (at most once a second,
as apps do), every Indoor Bike Data notification is kept (``--csv``), and at the end it prints
how the trainer followed: power error and the ERG response to each target step, by the rule the
report uses (settled within max(5 % of the target, 5 W) for 1 s; trainer reviews quote 3-5 s).
Against ``./bike run --ftms`` it is a closed loop through both ends of the protocol.

``--spindown`` starts the trainer's spin-down (FTMS op 0x13), prints the target speeds it answers
with, then its Fitness Machine Status (speed up, stop pedalling, success or error) and its speed
once a second, as an app's calibration screen does, until success or error.

Exit codes: 0 done; 1 no trainer there, it refused the target, or the spin-down failed or did
not finish within --seconds; 2 bad arguments.
"""
from __future__ import annotations

import math
import struct
import sys
import time

from bike_session import dircon, ftms

PROPS = {dircon.PROP_READ: "read", dircon.PROP_WRITE: "write", dircon.PROP_NOTIFY: "notify"}
RESULTS = {1: "success", 2: "not supported", 3: "invalid parameter", 4: "failed", 5: "control not permitted"}


def find(seconds: float = 3.0) -> list[tuple[str, str, int, str]]:
    """(name, address, port, ble-service-uuids) of the DIRCON trainers announced by mDNS."""
    from zeroconf import ServiceBrowser, Zeroconf

    found: dict[str, object] = {}

    class Listener:
        def add_service(self, zc, type_, name):
            found[name] = None

        def update_service(self, zc, type_, name):
            found[name] = None

        def remove_service(self, zc, type_, name):
            found.pop(name, None)

    zc = Zeroconf()
    try:
        ServiceBrowser(zc, dircon.MDNS_SERVICE, Listener())
        time.sleep(seconds)
        out = []
        for name in sorted(found):
            info = zc.get_service_info(dircon.MDNS_SERVICE, name, timeout=2000)
            if info is None:
                continue
            uuids = (info.properties or {}).get(b"ble-service-uuids", b"") or b""
            for address in info.parsed_addresses() or ["?"]:
                out.append((name.removesuffix("." + dircon.MDNS_SERVICE), address, info.port,
                            uuids.decode("ascii", "replace")))
        return out
    finally:
        zc.close()


def describe(app: dircon.DirconClient, say) -> bool:
    """Print the services and characteristics; True when the FTMS service is there."""
    services = app.request(dircon.MSG_DISCOVER_SERVICES).data
    has_ftms = False
    for i in range(0, len(services) - 15, 16):
        uuid = services[i:i + 16]
        say(f"service {dircon.uuid_text(uuid)}")
        has_ftms |= uuid == dircon.uuid128(ftms.FTMS_SERVICE)
        reply = app.request(dircon.MSG_DISCOVER_CHARACTERISTICS, uuid)
        records = reply.data[16:]
        for k in range(0, len(records) - 16, 17):
            props = records[k + 16]
            say(f"  characteristic {dircon.uuid_text(records[k:k + 16])}: "
                + ", ".join(text for bit, text in PROPS.items() if props & bit))
    if has_ftms:
        for uuid, label, scale, unit in ((ftms.POWER_RANGE, "power", 1, "W"),
                                         (ftms.INCLINATION_RANGE, "inclination", 0.1, "%"),
                                         (ftms.RESISTANCE_RANGE, "resistance level", 0.1, "")):
            try:
                lo, hi, step = struct.unpack("<hhH", app.read(uuid)[:6])
                unit_text = f" {unit}" if unit else ""
                say(f"{label} range {lo * scale:g} .. {hi * scale:g}{unit_text} in steps of {step * scale:g}")
            except (ValueError, struct.error):
                say(f"{label} range: not served")
        try:        # optional in FTMS (4.10); a trainer that serves it answers a read
            say(f"training status: {ftms.training_status_text(app.read(ftms.TRAINING_STATUS))}")
        except ValueError:
            say("training status: not served")
    return has_ftms


def trainer_error(text: str) -> None:
    """A refused or unfinished one-shot request: the command's one error line (stderr); it
    was a line among the others on stdout, no 'error:' (--level 500: 'invalid parameter')."""
    print(f"error: {text}", file=sys.stderr, flush=True)


def control(app: dircon.DirconClient, op: int, param: bytes, what: str, say) -> bool:
    app.subscribe(ftms.CONTROL_POINT)
    for code, text in ((ftms.OP_REQUEST_CONTROL, b""), (op, param)):
        reply = app.write(ftms.CONTROL_POINT, bytes([code]) + text)
        if reply.code != dircon.RESP_SUCCESS:
            trainer_error(f"the trainer refused the Control Point write (DIRCON code {reply.code})")
            return False
        response = app.wait_notification(ftms.CONTROL_POINT)
        result = response[2] if len(response) >= 3 else 0
        name = "request control" if code == ftms.OP_REQUEST_CONTROL else what
        if result != ftms.RESULT_SUCCESS:
            trainer_error(f"{name}: the trainer answered {RESULTS.get(result, f'result {result}')}")
            return False
        say(f"{name}: {RESULTS[result]}")
    return True


def spin_down(app: dircon.DirconClient, seconds: float, say) -> int:
    """Spin Down Control: start, print the target speeds and the progress; 0 on success."""
    for uuid in (ftms.CONTROL_POINT, ftms.STATUS, ftms.INDOOR_BIKE_DATA):
        app.subscribe(uuid)
    for code, param in ((ftms.OP_REQUEST_CONTROL, b""), (ftms.OP_SPIN_DOWN, b"\x01")):
        reply = app.write(ftms.CONTROL_POINT, bytes([code]) + param)
        if reply.code != dircon.RESP_SUCCESS:
            trainer_error(f"the trainer refused the Control Point write (DIRCON code {reply.code})")
            return 1
        response = app.wait_notification(ftms.CONTROL_POINT)
        result = response[2] if len(response) >= 3 else 0
        if result != ftms.RESULT_SUCCESS:
            trainer_error(f"{ftms.OP_NAMES[code]}: the trainer answered {RESULTS.get(result, f'result {result}')}")
            return 1
        say(f"{ftms.OP_NAMES[code]}: {RESULTS[result]}")
    if len(response) >= 7:
        low, high = struct.unpack_from("<HH", response, 3)
        say(f"spin down: speed up past {high / 100:g} km/h, then stop pedalling (coast to {low / 100:g} km/h)")
    end = time.monotonic() + seconds
    next_print = 0.0
    while time.monotonic() < end:
        for value in app.take_notifications(ftms.STATUS):
            if len(value) >= 2 and value[0] == ftms.STATUS_SPIN_DOWN:
                say(f"status: {ftms.SPIN_DOWN_NAMES.get(value[1], f'spin down status {value[1]}')}")
                if value[1] in (ftms.SPIN_DOWN_SUCCESS, ftms.SPIN_DOWN_ERROR):
                    return 0 if value[1] == ftms.SPIN_DOWN_SUCCESS else 1
        try:
            data = app.wait_notification(ftms.INDOOR_BIKE_DATA, max(0.1, min(1.0, end - time.monotonic())))
        except TimeoutError:
            continue
        if time.monotonic() >= next_print:
            next_print = time.monotonic() + 1.0
            try:
                fields = ftms.parse_indoor_bike_data(data)
                say(f"speed {fields.get('speed_kmh', float('nan')):.1f} km/h, cadence "
                    f"{fields.get('cadence_rpm', float('nan')):g} rpm")
            except ValueError as exc:
                say(f"indoor bike data: {exc}")
    trainer_error(f"the spin-down did not finish within {seconds:g} s")
    return 1


def _ranges(app: dircon.DirconClient):
    """The trainer's Command ranges (ModeUnits) from its FTMS range characteristics."""
    from bike_session.profiles import ModeUnits
    lo_w, hi_w, _ = struct.unpack("<hhH", app.read(ftms.POWER_RANGE)[:6])
    try:
        lo_g, hi_g, _ = struct.unpack("<hhH", app.read(ftms.INCLINATION_RANGE)[:6])
    except ValueError:
        lo_g, hi_g = 0, 0
    return ModeUnits(float(hi_w), lo_g / 1000.0, hi_g / 1000.0 if hi_g > lo_g else lo_g / 1000.0 + 1e-3, 0.0, 1.0)


def workout_problem(opts) -> str | None:
    """Why --workout cannot be ridden on any trainer (a file that is not a workout, a bad --ftp
    or --max-hr), found before connecting: it was found only once a trainer answered. Read
    against the widest ranges the FTMS fields carry; ride_workout reads it again against the
    trainer's own (where a target beyond them is said)."""
    import warnings

    from bike_session.cli import rider_options_problem
    from bike_session.profiles import ModeUnits, ProfileError
    from bike_session.workouts import load_workout

    # the options' own error, as ./bike run's: a .zwo's was "bad workout: FILE: ftp_w: parameter ftp_w must
    # be ...", and a .yaml profile (no relative targets) took --ftp 5000 without a word
    rider = rider_options_problem(opts.ftp, getattr(opts, "max_hr", None))
    if rider:
        return rider
    widest = ModeUnits(float(0x7FFF), -0x8000 / 1000.0, 0x7FFF / 1000.0, 0.0, 1.0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            load_workout(opts.workout, ftp_w=opts.ftp, pmax_w=widest.erg_power_max_w, units=widest,
                         max_hr_bpm=getattr(opts, "max_hr", None))
    except ProfileError as exc:
        return f"bad workout: {exc}"
    return None


# the road an app sends with a grade unless told otherwise: Zwift's (Crr 0.004, Cw 0.51 kg/m, no wind)
DEFAULT_ROAD = (0.004, 0.51, 0.0)


def simulation_road_problem(road, prefix: str = "--") -> str | None:
    """Why (crr, cw_kg_m, wind_mps) does not fit the Indoor Bike Simulation's fields (narrower
    than what a Command may carry, bike_plant.mechanics.road_problem)."""
    crr, cw, wind = road
    for name, value, lo, hi in (("crr", crr, 0.0, 0.0255), ("cw", cw, 0.0, 2.55), ("wind", wind, -32.767, 32.767)):
        if not lo <= value <= hi:          # also NaN
            return f"{prefix}{name} {value:g} outside [{lo:g}, {hi:g}] (the FTMS Indoor Bike Simulation's field)"
    return None


CADENCE_FIELD_MAX_RPM = 0xFFFF / 2      # Set Targeted Cadence: uint16 in 0.5 rpm


def target_problem(opts) -> str | None:
    """Why --power / --grade (as sent, after --difficulty) / --level does not fit the sint16 field
    it is written in (NaN and out-of-field values ended in a ValueError / struct.error traceback
    after connecting), and why --port is no TCP port."""
    if not 1 <= opts.port <= 65535:
        return f"--port must be 1..65535, got {opts.port}"
    fields = (("power", opts.power, opts.power, 1, 0.0, "W"),
              ("grade", opts.grade, None if opts.grade is None else sent_grade_pct(opts.grade, opts.difficulty),
               100, -327.68, "%"),
              ("level", opts.level, opts.level, 10, 0.0, ""))
    for name, given, sent, scale, lo, unit in fields:
        if given is None:
            continue
        hi = 0x7FFF / scale
        if not (math.isfinite(sent) and lo * scale <= round(sent * scale) <= 0x7FFF):
            what = "" if sent is given or sent == given else f" (sent as {sent:g})"
            return f"--{name} {given:g}{what} outside [{lo:g}, {hi:g}]{' ' + unit if unit else ''} (the FTMS field)"
    return None


def simulation_param(grade_pct: float, road=DEFAULT_ROAD) -> bytes:
    """Indoor Bike Simulation parameters: wind 0.001 m/s, grade 0.01 %, Crr 1e-4, Cw 0.01 kg/m."""
    crr, cw, wind = road
    return struct.pack("<hhBB", round(wind * 1000), round(grade_pct * 100), round(crr * 1e4), round(cw * 100))


def cadence_param(cadence_rpm: float) -> bytes:
    """Set Targeted Cadence's parameter: uint16 in 0.5 rpm (0 .. CADENCE_FIELD_MAX_RPM)."""
    return struct.pack("<H", round(cadence_rpm * 2))


def sent_grade_pct(grade_pct: float, difficulty_pct: float | None) -> float:
    """The grade an app sends for a road's ``grade_pct``: as it is, or, with Zwift's trainer
    difficulty, scaled by it and halved again downhill (research notes, trainers.md section 3:
    -10 % in game is sent as -2.5 % at the default 50 %)."""
    if difficulty_pct is None:
        return grade_pct
    scaled = grade_pct * difficulty_pct / 100.0
    return 0.5 * scaled if scaled < 0.0 else scaled


def _target_write(mode: int, command: float, units, road=DEFAULT_ROAD,
                  difficulty_pct: float | None = None, heart_rate_bpm: float = 0.0) -> tuple[int, bytes, str] | None:
    """The Control Point write for a profile's Command (None: a mode FTMS cannot ask for); an ERG
    step with a heart-rate target sends that (FTMS Set Target Heart Rate: the trainer's power
    follows it, from the power it was holding)."""
    from bike_session.profiles import MODES
    if mode == MODES["erg"] and heart_rate_bpm:
        bpm = round(heart_rate_bpm)
        return ftms.OP_TARGET_HEART_RATE, bytes([bpm]), f"target heart rate {bpm} bpm"
    if mode == MODES["erg"]:
        watts = round(units.target_of(mode, command)[0])
        return ftms.OP_TARGET_POWER, struct.pack("<h", watts), f"target power {watts} W"
    if mode == MODES["slope"]:
        grade_pct = units.target_of(mode, command)[0]
        sent = sent_grade_pct(grade_pct, difficulty_pct)
        said = f"{sent:.1f} %" if difficulty_pct is None else f"{sent:.2f} % ({grade_pct:.1f} % at difficulty " \
                                                             f"{difficulty_pct:g} %)"
        return (ftms.OP_SIMULATION, simulation_param(sent, road),
                f"simulation grade {said} (Crr {road[0]:g}, Cw {road[1]:g} kg/m, wind {road[2]:g} m/s)")
    if mode == MODES["spindown"]:
        return ftms.OP_SPIN_DOWN, b"\x01", "spin down control: start"
    if mode == MODES["resistance"]:
        level = round(command * ftms.RESISTANCE_LEVEL_MAX * 10)
        return ftms.OP_TARGET_RESISTANCE, struct.pack("<h", level), f"resistance level {level / 10:g}"
    return None


def erg_steps(t_s, target_w, power_w, hold_s: float | None = None) -> list[tuple[float, float, float | None]]:
    """(time, new target, settle time or None) of each ERG target step in a ride's samples: a
    change of more than max(10 W, 5 %); settled from the first sample after which the power
    stays within max(5 % of the target, 5 W) for ``hold_s`` (the report's rule, report.ERG_*)."""
    from bike_session.report import ERG_HOLD_S, ERG_STEP_W, ERG_TOL, ERG_TOL_MIN_W
    hold_s = ERG_HOLD_S if hold_s is None else hold_s
    out = []
    starts = [i for i in range(1, len(t_s)) if target_w[i] is not None and target_w[i - 1] is not None
              and abs(target_w[i] - target_w[i - 1]) > max(ERG_STEP_W, ERG_TOL * abs(target_w[i - 1]))]
    for n, i in enumerate(starts):
        end = starts[n + 1] if n + 1 < len(starts) else len(t_s)
        band = max(ERG_TOL * abs(target_w[i]), ERG_TOL_MIN_W)
        settle = None
        first_in = None
        for k in range(i, end):
            if abs(power_w[k] - target_w[i]) <= band:
                first_in = k if first_in is None else first_in
                if t_s[k] - t_s[first_in] >= hold_s:
                    settle = t_s[first_in] - t_s[i]
                    break
            else:
                first_in = None
        out.append((t_s[i], target_w[i], settle))
    return out


def ride_workout(app: dircon.DirconClient, opts, say) -> int:
    """Ride ``opts.workout`` on the trainer (see the module's docstring)."""
    import csv

    import warnings

    from bike_session.profiles import MODE_NAMES, MODES, ProfileError
    from bike_session.workouts import WorkoutWarning, load_workout

    units = _ranges(app)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", WorkoutWarning)
            profile = load_workout(opts.workout, ftp_w=opts.ftp, pmax_w=units.erg_power_max_w, units=units,
                                   max_hr_bpm=getattr(opts, "max_hr", None))
    except ProfileError as exc:
        print(f"error: bad workout: {exc}", file=sys.stderr)
        return 2
    for w in caught:
        say(f"warning: {w.message}")
    for seg in profile.segments:            # a profile's road may lie beyond the FTMS fields
        problem = simulation_road_problem(profile.road_at(seg.start_s) or opts.road, prefix="road ")
        if problem:
            print(f"error: bad workout: {seg.path}: {problem}", file=sys.stderr)
            return 2
    seconds = profile.duration_s if not opts.seconds_given else opts.seconds
    say(f"workout {profile.name!r}: {profile.duration_s:g} s (riding {seconds:g} s) on a trainer of "
        f"0 .. {units.erg_power_max_w:g} W")
    if not control(app, ftms.OP_START_RESUME, b"", "start", say):
        return 1
    app.subscribe(ftms.INDOOR_BIKE_DATA)
    rows = []
    sent = None
    sent_cadence = 0.0
    next_write = 0.0
    t0 = time.monotonic()
    while True:
        now = time.monotonic() - t0
        if now >= seconds:
            break
        cmd, mode, _, label = profile.command_at(now)
        target = _target_write(mode, cmd, units, profile.road_at(now) or opts.road, opts.difficulty,
                               profile.heart_rate_at(now) or 0.0)
        if target is None:
            say(f"warning: t = {now:.0f} s: mode {MODE_NAMES.get(mode, mode)} has no FTMS target; not sent")
        elif target[:2] != sent and now >= next_write:
            reply = app.write(ftms.CONTROL_POINT, bytes([target[0]]) + target[1])
            result = app.wait_notification(ftms.CONTROL_POINT)
            ok = reply.code == dircon.RESP_SUCCESS and len(result) >= 3 and result[2] == ftms.RESULT_SUCCESS
            say(f"t = {now:5.1f} s  {target[2]}" + ("" if ok else f": refused ({result.hex()})"))
            sent, next_write = target[:2], now + 1.0
        cadence = profile.cadence_at(now) or 0.0
        if sent is not None and cadence != sent_cadence:
            # the step's cadence target, as apps show it (FTMS Set Targeted Cadence)
            app.write(ftms.CONTROL_POINT, bytes([ftms.OP_TARGETED_CADENCE]) + cadence_param(cadence))
            result = app.wait_notification(ftms.CONTROL_POINT)
            ok = len(result) >= 3 and result[2] == ftms.RESULT_SUCCESS
            say(f"t = {now:5.1f} s  targeted cadence {cadence:g} rpm" + ("" if ok else f": refused ({result.hex()})"))
            sent_cadence = cadence
        try:
            value = app.wait_notification(ftms.INDOOR_BIKE_DATA, max(0.05, min(1.0, seconds - now)))
        except TimeoutError:
            continue
        fields = ftms.parse_indoor_bike_data(value)
        t = time.monotonic() - t0
        cmd, mode, _, _ = profile.command_at(t)
        # (a heart-rate target has no power target: the trainer's power follows the heart)
        target_w = units.target_of(mode, cmd)[0] if mode == MODES["erg"] and not profile.heart_rate_at(t) else None
        rows.append({"t_s": round(t, 3), "target_w": None if target_w is None else round(target_w, 1), **fields})
    control(app, ftms.OP_STOP_PAUSE, b"\x01", "stop", say)
    if opts.csv:
        keys = sorted({k for r in rows for k in r}, key=lambda k: (k not in ("t_s", "target_w"), k))
        with open(opts.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys)
            writer.writeheader()
            writer.writerows(rows)
        say(f"{len(rows)} Indoor Bike Data samples written to {opts.csv}")
    erg = [r for r in rows if r["target_w"] is not None and "power_w" in r]
    if erg:
        err = [r["power_w"] - r["target_w"] for r in erg]
        rms = (sum(e * e for e in err) / len(err)) ** 0.5
        say(f"ERG: {len(erg)} samples, power - target mean {sum(err) / len(err):+.1f} W, rms {rms:.1f} W")
        steps = erg_steps([r["t_s"] for r in erg], [r["target_w"] for r in erg], [r["power_w"] for r in erg])
        for t, w, settle in steps:
            say(f"  step to {w:.0f} W at {t:.1f} s: " + (f"settled in {settle:.1f} s" if settle is not None
                                                        else "not settled"))
        done = sorted(s for _, _, s in steps if s is not None)
        if done:
            say(f"ERG response: {len(steps)} steps, {len(done)} settled, median {done[len(done) // 2]:.1f} s, "
                f"max {done[-1]:.1f} s (trainer reviews: 3-5 s)")
    return 0


def main(opts) -> int:
    def say(text: str) -> None:
        print(text, flush=True)

    if opts.find:
        trainers = find(opts.seconds if opts.seconds_given else 3.0)
        for name, address, port, uuids in trainers:
            say(f"{name}: {address}:{port} services {uuids}")
        if not trainers:
            say("no DIRCON trainer announced (mDNS _wahoo-fitness-tnp._tcp) on this network")
        return 0
    targets = [t for t in (opts.power, opts.grade, opts.level, opts.workout, opts.spindown or None) if t is not None]
    if len(targets) > 1:
        print("error: give one of --power, --grade, --level, --workout, --spindown", file=sys.stderr)
        return 2
    # the road and the difficulty go with a grade (--grade, a workout's slope segments) only:
    # given with --power they were dropped without a word
    given = [name for name, value in (("--crr", opts.crr), ("--cw", opts.cw), ("--wind", opts.wind),
                                      ("--difficulty", opts.difficulty)) if value is not None]
    if given and opts.grade is None and not opts.workout:
        print(f"error: {', '.join(given)}: only with --grade or --workout (the road and the difficulty a grade "
              "is sent with)", file=sys.stderr)
        return 2
    opts.road = tuple(default if value is None else value
                      for default, value in zip(DEFAULT_ROAD, (opts.crr, opts.cw, opts.wind)))
    problem = simulation_road_problem(opts.road)
    if problem is None and opts.difficulty is not None and not 0.0 <= opts.difficulty <= 100.0:
        problem = f"--difficulty {opts.difficulty:g} outside [0, 100] %"
    if problem is None and opts.cadence is not None and not 0.0 <= opts.cadence <= CADENCE_FIELD_MAX_RPM:
        problem = f"--cadence {opts.cadence:g} outside [0, {CADENCE_FIELD_MAX_RPM:g}] (the FTMS field)"
    if problem is None:
        problem = target_problem(opts)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    if opts.csv and not opts.workout:
        print("error: --csv needs --workout", file=sys.stderr)
        return 2
    problem = workout_problem(opts) if opts.workout else None
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        app = dircon.DirconClient(opts.host, opts.port)
    except OSError as exc:
        print(f"error: no trainer at {opts.host}:{opts.port} ({exc.strerror or exc})", file=sys.stderr)
        return 1
    try:
        if not describe(app, say):
            say("no Fitness Machine Service (0x1826) here: nothing to control")
            return 1
        if opts.workout:
            return ride_workout(app, opts, say)
        if opts.spindown:
            return spin_down(app, opts.seconds, say)
        if opts.power is not None:
            ok = control(app, ftms.OP_TARGET_POWER, struct.pack("<h", round(opts.power)),
                         f"target power {round(opts.power)} W", say)
        elif opts.grade is not None:
            sent = sent_grade_pct(opts.grade, opts.difficulty)
            ok = control(app, ftms.OP_SIMULATION, simulation_param(sent, opts.road),
                         f"simulation grade {sent:g} %" + ("" if opts.difficulty is None else
                                                          f" ({opts.grade:g} % at difficulty {opts.difficulty:g} %)"),
                         say)
        elif opts.level is not None:
            ok = control(app, ftms.OP_TARGET_RESISTANCE, struct.pack("<h", round(opts.level * 10)),
                         f"resistance level {opts.level:g}", say)
        else:
            ok = True
        if ok and opts.cadence is not None:
            ok = control(app, ftms.OP_TARGETED_CADENCE, cadence_param(opts.cadence),
                         f"targeted cadence {opts.cadence:g} rpm", say)
        if not ok:
            return 1
        app.subscribe(ftms.INDOOR_BIKE_DATA)
        app.subscribe(ftms.TRAINING_STATUS)       # a trainer without it refuses: nothing to print then
        end = time.monotonic() + opts.seconds
        next_print = 0.0
        while time.monotonic() < end:
            try:
                value = app.wait_notification(ftms.INDOOR_BIKE_DATA, max(0.1, end - time.monotonic()))
            except TimeoutError:
                break
            for status in app.take_notifications(ftms.TRAINING_STATUS):
                try:
                    say(f"training status: {ftms.training_status_text(status)}")
                except ValueError as exc:
                    say(f"training status: {exc}")
            if time.monotonic() < next_print:
                continue
            next_print = time.monotonic() + 1.0
            try:
                fields = ftms.parse_indoor_bike_data(value)
            except ValueError as exc:
                say(f"indoor bike data: {exc}")
                continue
            say("indoor bike data: " + ", ".join(f"{k} {v:g}" for k, v in fields.items()))
        return 0
    except (OSError, ConnectionError, TimeoutError) as exc:
        print(f"error: the trainer at {opts.host}:{opts.port}: {exc}", file=sys.stderr)
        return 1
    finally:
        app.close()
