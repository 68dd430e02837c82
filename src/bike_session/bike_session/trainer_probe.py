"""`./bike trainer`: the app's end of FTMS over DIRCON, for a quick look at a trainer on the
network, this testbed's (`./bike run --ftms`) or a real one (a KICKR, a Neo, a SmartSpin2k):
find trainers by mDNS, list a trainer's services, characteristics and FTMS ranges, optionally
take control and set a target, and print the Indoor Bike Data it notifies, once a second.

    ./bike trainer --find                         # trainers announced on the network (3 s)
    ./bike trainer [--host H] [--port P]          # what the trainer at H:P serves, then 5 s of data
    ./bike trainer --power 200 --seconds 30       # ERG at 200 W (Request Control first)
    ./bike trainer --grade 4.5                    # simulation grade 4.5 %

Exit codes: 0 done; 1 no trainer there, or it refused the target; 2 bad arguments.
"""
from __future__ import annotations

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
                say(f"{label} range {lo * scale:g} .. {hi * scale:g} {unit} in steps of {step * scale:g}".rstrip())
            except (ValueError, struct.error):
                say(f"{label} range: not served")
    return has_ftms


def control(app: dircon.DirconClient, op: int, param: bytes, what: str, say) -> bool:
    app.subscribe(ftms.CONTROL_POINT)
    for code, text in ((ftms.OP_REQUEST_CONTROL, b""), (op, param)):
        reply = app.write(ftms.CONTROL_POINT, bytes([code]) + text)
        if reply.code != dircon.RESP_SUCCESS:
            say(f"error: the trainer refused the Control Point write (DIRCON code {reply.code})")
            return False
        response = app.wait_notification(ftms.CONTROL_POINT)
        result = response[2] if len(response) >= 3 else 0
        name = "request control" if code == ftms.OP_REQUEST_CONTROL else what
        say(f"{name}: {RESULTS.get(result, f'result {result}')}")
        if result != ftms.RESULT_SUCCESS:
            return False
    return True


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
    targets = [t for t in (opts.power, opts.grade, opts.level) if t is not None]
    if len(targets) > 1:
        print("error: give one of --power, --grade, --level", file=sys.stderr)
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
        if opts.power is not None:
            ok = control(app, ftms.OP_TARGET_POWER, struct.pack("<h", round(opts.power)),
                         f"target power {round(opts.power)} W", say)
        elif opts.grade is not None:
            ok = control(app, ftms.OP_SIMULATION, struct.pack("<hhBB", 0, round(opts.grade * 100), 40, 51),
                         f"simulation grade {opts.grade:g} %", say)
        elif opts.level is not None:
            ok = control(app, ftms.OP_TARGET_RESISTANCE, struct.pack("<h", round(opts.level * 10)),
                         f"resistance level {opts.level:g}", say)
        else:
            ok = True
        if not ok:
            return 1
        app.subscribe(ftms.INDOOR_BIKE_DATA)
        end = time.monotonic() + opts.seconds
        next_print = 0.0
        while time.monotonic() < end:
            try:
                value = app.wait_notification(ftms.INDOOR_BIKE_DATA, max(0.1, end - time.monotonic()))
            except TimeoutError:
                break
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
