"""Workout files (.zwo, .erg, .mrc) imported as profiles: timelines, FTP scaling, Pmax, malformed files."""
import math
import pathlib
import re
import warnings

import pytest

from bike_session.profiles import MAX_LEAF_SEGMENTS, Profile, ProfileError, load_profile
from bike_session.workouts import (MAX_WORKOUT_BYTES, MAX_XML_DEPTH, MAX_XML_ELEMENTS, TextEvent, Workout,
                                   WorkoutError, WorkoutSegment, WorkoutWarning, describe, load_workout,
                                   parse_workout_bytes, pmax_w_from_config)

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "test" / "data" / "workouts"
BAD = DATA / "bad"
PMAX = 1016.68          # controller.pmax_w of config/bldc_default.yaml


def write(tmp_path, text, name):
    path = tmp_path / name
    path.write_text(text)
    return path


def zwo(blocks: str, head: str = "") -> str:
    return f"<workout_file>{head}<workout>\n{blocks}\n</workout></workout_file>\n"


def check_timeline(p: Profile):
    """The invariants the session node relies on."""
    assert [s.index for s in p.segments] == list(range(len(p.segments)))
    for a, b in zip(p.segments, p.segments[1:]):
        assert b.start_s == pytest.approx(a.end_s, abs=1e-9)
    for s in p.segments:
        assert 0.0 <= s.start <= 1.0 and 0.0 <= s.end <= 1.0 and s.duration_s > 0


# --------------------------------------------------------------------------- ZWO


def test_pmax_default_matches_config():
    from bike_plant.config import load_config
    assert pmax_w_from_config(load_config(ROOT / "config" / "bldc_default.yaml")) == PMAX
    with pytest.raises(WorkoutError, match="controller.pmax_w"):
        pmax_w_from_config({"controller": {}})


def test_zwo_every_element():
    w = load_workout(DATA / "over_unders.zwo", ftp_w=250, pmax_w=PMAX)
    assert isinstance(w, Workout) and isinstance(w, Profile)
    check_timeline(w)
    assert (w.name, w.author, w.format) == ("Testbed Over-Unders", "bike testbed", "zwo")
    assert "over-unders & ramps" in w.description
    assert w.duration_s == 3000.0
    assert len(w.segments) == 19
    assert w.warnings == []
    tw = w.target_w_at
    # Warmup: linear 0.40 -> 0.75 FTP over 600 s
    assert tw(0) == pytest.approx(100.0)
    assert tw(300) == pytest.approx(143.75)
    assert tw(599.999) == pytest.approx(187.5, abs=1e-3)
    assert tw(600) == pytest.approx(162.5)                    # SteadyState Power
    assert tw(950) == pytest.approx(212.5)                    # SteadyState PowerLow/High -> mean
    # IntervalsT Repeat 4 (60 on 105 %, 30 off 55 %) from 1020 s, then Repeat 2 x 120 s ramp 90->100 %, no off
    iv = [s for s in w.segments if s.block == "IntervalsT"]
    assert len(iv) == 4 * 2 + 2
    assert [s.label for s in iv[:8]] == ["IntervalsT on", "IntervalsT off"] * 4
    assert [s.path for s in iv[:2]] == ["workout[3] line 20 <IntervalsT> on (repeat 1/4)",
                                        "workout[3] line 20 <IntervalsT> off (repeat 1/4)"]
    for k in range(4):
        assert tw(1020 + 90 * k + 30) == pytest.approx(262.5)
        assert tw(1020 + 90 * k + 75) == pytest.approx(137.5)
    assert tw(1440) == pytest.approx(237.5) and tw(1560) == pytest.approx(237.5)
    assert tw(1650) == pytest.approx(125.0)                   # SolidState
    assert tw(1830) == pytest.approx(187.5)                   # Ramp 0.60 -> 0.90, half way
    # FreeRide / MaxEffort: no target, fixed resistance-mode Command
    assert tw(2000) is None and w.command_at(2000)[:2] == (0.2, 0)
    assert tw(2290) is None and w.command_at(2290) == (0.5, 0, 16, "MaxEffort")
    assert w.command_at(2350)[0] == 0.2 and w.cadence_at(2350) == 85.0      # Freeride, CadenceLow/High mean
    # Cooldown 0.65 -> 0.35 descends
    assert tw(2400) == pytest.approx(162.5) and tw(2700) == pytest.approx(125.0)
    assert w.command_at(3000) == (0.0, 2, 19, "end") and tw(3000) is None
    # Command = W / Pmax, ERG mode
    for t in (0, 300, 1050, 1095, 1440, 1830, 2700):
        cmd, mode, _, _ = w.command_at(t)
        assert cmd == pytest.approx(tw(t) / PMAX) and mode == 2
    # cadence targets
    assert (w.cadence_at(0), w.cadence_at(600), w.cadence_at(950)) == (85.0, 90.0, None)
    assert (w.cadence_at(1030), w.cadence_at(1090), w.cadence_at(1400)) == (100.0, 85.0, None)
    # text events, absolute times (block start + timeoffset; IntervalsT: start of the block)
    assert [(e.time_s, e.message) for e in w.events] == [
        (0.0, "Welcome! Ten minutes to warm up."), (540.0, "One minute to go"),
        (1020.0, "Four over-unders: 60 s hard, 30 s easy"), (1350.0, "Last one!"),
        (1990.0, "Ride as you like"), (2410.0, "Easy now")]
    assert w.events[1].duration_s == 10.0 and w.events[1].where == "line 16 <textevent>"
    assert [e.message for e in w.events_between(1000, 1400)] == ["Four over-unders: 60 s hard, 30 s easy", "Last one!"]
    info = w.info()
    assert info["ftp_w"] == 250 and info["pmax_w"] == PMAX and len(info["events"]) == 6
    assert "Testbed Over-Unders" in describe(w)
    assert len(w.timeline(1.0)) == 3001


def test_zwo_research_example():
    # the hand-written file of trainers.md 1.1 and its expected expansion (s -> % FTP)
    text = """<workout_file>
  <author>testbed</author><name>zwo-smoke</name><sportType>bike</sportType>
  <workout>
    <Warmup Duration="120" PowerLow="0.40" PowerHigh="0.70"/>
    <SteadyState Duration="60" Power="0.75" Cadence="90"/>
    <IntervalsT Repeat="3" OnDuration="30" OffDuration="30" OnPower="1.10" OffPower="0.50"
                Cadence="100" CadenceResting="85"/>
    <Ramp Duration="60" PowerLow="0.60" PowerHigh="0.90"/>
    <FreeRide Duration="60" FlatRoad="1"/>
    <Cooldown Duration="120" PowerLow="0.65" PowerHigh="0.35">
      <textevent timeoffset="10" message="Easy now" duration="5"/>
    </Cooldown>
  </workout>
</workout_file>"""
    w = parse_workout_bytes(text, "zwo", ftp_w=100, pmax_w=PMAX)
    check_timeline(w)
    assert w.duration_s == 600
    pct = w.target_w_at     # FTP 100 W: watts == percent
    assert pct(0) == pytest.approx(40) and pct(60) == pytest.approx(55) and pct(150) == pytest.approx(75)
    for k in range(6):
        assert pct(180 + 30 * k + 15) == pytest.approx(110 if k % 2 == 0 else 50)
    assert pct(390) == pytest.approx(75) and pct(450) is None
    assert pct(480) == pytest.approx(65) and pct(540) == pytest.approx(50)
    assert w.events == [TextEvent(490.0, "Easy now", 5.0, "line 11 <textevent>")]


def test_zwo_variants(tmp_path):
    text = zwo("""
<Cooldown Duration="100" PowerLow="0.3" PowerHigh="0.7"/>
<cooldown duration="100" power="0.5"/>
<INTERVALST REPEAT="2" ONDURATION="10" OFFDURATION="0" ONPOWER="1"/>
<steadystate Duration="10.5" Power="0.5"><TextEvent TimeOffset="1" mssage="typo in Zwift files"/>
  <TextNotification timeOffset="2" text="notification"/></steadystate>
""", head="<ftpOverride>300</ftpOverride><unknownMeta>ignored</unknownMeta><sportType>Bike</sportType>")
    path = write(tmp_path, text, "v.zwo")
    w = load_workout(path, ftp_w=200, pmax_w=PMAX)
    assert w.name == "v" and w.file_ftp_w == 300 and w.ftp_w == 200
    assert w.target_w_at(0) == pytest.approx(140) and w.target_w_at(50) == pytest.approx(100)   # swapped: descends
    assert w.target_w_at(150) == pytest.approx(100)
    assert len(w.segments) == 2 + 2 + 1 and w.duration_s == 230.5
    assert [(e.time_s, e.message) for e in w.events] == [(221.0, "typo in Zwift files"), (222.0, "notification")]
    assert load_workout(path, ftp_w=200, pmax_w=PMAX, use_file_ftp=True).target_w_at(150) == pytest.approx(150)
    assert load_workout(path, pmax_w=PMAX).target_w_at(150) == pytest.approx(150)     # no rider FTP: file's



@pytest.mark.parametrize("declaration", ["", '<?xml version="1.0" encoding="UTF-8"?>\r\n'])
def test_zwo_saved_in_a_windows_code_page_is_read(tmp_path, declaration):
    # a .zwo whose description was edited in a Windows editor saving ANSI (cp1252): expat refused
    # the whole file ("not well-formed (invalid token)"); the .erg reader reads such text already
    text = declaration + zwo('<SteadyState Duration="60" Power="0.75"><textevent timeoffset="5" message="Allez, '
                             '\u00e9t\u00e9 \u2013 go"/></SteadyState>', head="<name>Caf\u00e9 \u2013 Sweet spot</name>")
    path = tmp_path / "cp.zwo"
    path.write_bytes(text.encode("cp1252"))
    w = load_workout(path, ftp_w=200, pmax_w=PMAX)
    assert w.name == "Caf\u00e9 \u2013 Sweet spot" and w.target_w_at(10) == pytest.approx(150)
    assert [e.message for e in w.events] == ["Allez, \u00e9t\u00e9 \u2013 go"]
    # a file that declares its encoding, or is UTF-16 with a byte order mark, is read as it says
    path.write_bytes(text.replace(declaration, "").encode("utf-16"))
    assert load_workout(path, ftp_w=200, pmax_w=PMAX).name == "Caf\u00e9 \u2013 Sweet spot"
    path.write_bytes(('<?xml version="1.0" encoding="ISO-8859-1"?>' + text.replace(declaration, "")
                      .replace("\u2013", "-")).encode("latin-1"))
    assert load_workout(path, ftp_w=200, pmax_w=PMAX).name == "Caf\u00e9 - Sweet spot"


def test_zwo_with_blank_lines_before_the_xml_declaration_is_read(tmp_path):
    # a web page's template writes a newline before '<?xml ...?>': expat refused the file with
    # 'XML or text declaration not at start of entity'
    for bom in (b"", b"\xef\xbb\xbf"):
        path = tmp_path / "late.zwo"
        path.write_bytes(bom + b'\r\n\r\n<?xml version="1.0" encoding="UTF-8"?>\r\n'
                         + zwo('<SteadyState Duration="60" Power="0.75"/>').encode())
        assert load_workout(path, ftp_w=200, pmax_w=PMAX).target_w_at(10) == pytest.approx(150)
        path.write_bytes(bom + b'\n\n<?xml version="1.0"?>\n' + zwo('<SteadyState Duration="x" Power="0.75"/>').encode())
        with pytest.raises(WorkoutError, match=r"late.zwo: line 5 <SteadyState> attribute Duration"):
            load_workout(path, ftp_w=200, pmax_w=PMAX)


@pytest.mark.parametrize("encoding", ["U-8", "shift_jis", "utf-32"])
def test_zwo_declaring_an_encoding_the_reader_cannot_read_is_one_error(encoding):
    # a declared encoding Python does not know (LookupError) or expat cannot read (ValueError:
    # multi-byte) escaped the reader as a traceback
    data = f'<?xml version="1.0" encoding="{encoding}"?>\n' + zwo('<SteadyState Duration="60" Power="0.5"/>')
    with pytest.raises(WorkoutError, match=rf"enc.zwo: line 1: the XML declaration names encoding '{encoding}', "
                                           r"which this reader cannot read \(.*\); save the file as UTF-8"):
        parse_workout_bytes(data, "zwo", source="enc.zwo", ftp_w=200, pmax_w=PMAX)

def test_over_range_warns_and_saturates():
    text = zwo('<Ramp Duration="100" PowerLow="0.5" PowerHigh="1.5"/>\n<SteadyState Duration="50" Power="1.2"/>')
    with pytest.warns(WorkoutWarning, match=r"exceeds the machine's power range Pmax = 400 W") as rec:
        w = parse_workout_bytes(text, "zwo", source="hard.zwo", ftp_w=400, pmax_w=400)
    msgs = [str(r.message) for r in rec]
    assert len(msgs) == 2
    assert msgs[0].startswith("hard.zwo: line 2 <Ramp>: target 600 W exceeds") and "for 50 s" in msgs[0]
    assert msgs[1].startswith("hard.zwo: line 3 <SteadyState>: target 480 W exceeds") and "for 50 s" in msgs[1]
    assert len(w.warnings) == 2
    check_timeline(w)
    # the ramp 200 -> 600 W crosses Pmax = 400 W half way: linear up to Command 1, then held
    assert len(w.segments) == 3 and w.segments[0].end_s == pytest.approx(50)
    assert w.command_at(25)[0] == pytest.approx(0.75)
    assert w.command_at(75)[0] == 1.0 and w.target_w_at(75) == pytest.approx(500)
    assert w.command_at(120)[0] == 1.0 and w.target_w_at(120) == pytest.approx(480)
    with pytest.raises(WorkoutError, match=r"hard.zwo: line 2 <Ramp>: target 600 W exceeds"):
        parse_workout_bytes(text, "zwo", source="hard.zwo", ftp_w=400, pmax_w=400, over_range="error")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parse_workout_bytes(text, "zwo", ftp_w=200, pmax_w=400)     # 100..300 W: no warning


def test_mode_and_free_commands():
    text = zwo('<SteadyState Duration="10" Power="1"/><FreeRide Duration="10"/><MaxEffort Duration="5"/>')
    w = parse_workout_bytes(text, "zwo", ftp_w=200, pmax_w=1000, mode="motoring", freeride_command=0.1,
                            maxeffort_command=0.9)
    assert w.command_at(0) == (0.2, 1, 0, "SteadyState")
    assert w.command_at(10) == (0.1, 0, 1, "FreeRide")       # free segments always in resistance mode
    assert w.command_at(20) == (0.9, 0, 2, "MaxEffort")


# --------------------------------------------------------------------------- ERG / MRC


def test_erg_rescaled_to_rider_ftp():
    w = load_workout(DATA / "erg_smoke.erg", ftp_w=250, pmax_w=PMAX)
    check_timeline(w)
    assert (w.name, w.format, w.file_ftp_w, w.ftp_w) == ("erg-smoke", "erg", 200, 250)
    assert w.description.startswith("erg-smoke")
    assert w.duration_s == 180 and len(w.segments) == 3
    k = 250 / 200
    assert w.target_w_at(0) == pytest.approx(100 * k)
    assert w.target_w_at(60) == pytest.approx(120 * k)        # ramp 100 -> 140 W half way
    assert w.target_w_at(120) == pytest.approx(220 * k)       # the step at 2.00 min belongs to the effort
    assert w.target_w_at(149.9) == pytest.approx(220 * k)
    assert w.target_w_at(150) == pytest.approx(100 * k) and w.target_w_at(180) is None
    assert w.command_at(130)[0] == pytest.approx(220 * k / PMAX)
    assert [(e.time_s, e.message, e.duration_s) for e in w.events] == [
        (0.0, "Warm up", 10.0), (120.0, "LAP effort", 0.0), (120.0, "Go hard!", 5.0)]
    # the file's own FTP, or no rider FTP: watts as written
    for kw in ({"ftp_w": 250, "use_file_ftp": True}, {"ftp_w": None}, {"ftp_w": 200}):
        assert load_workout(DATA / "erg_smoke.erg", pmax_w=PMAX, **kw).target_w_at(60) == pytest.approx(120)


def test_mrc_is_percent_of_ftp():
    m = load_workout(DATA / "mrc_smoke.mrc", ftp_w=200, pmax_w=PMAX)
    e = load_workout(DATA / "erg_smoke.erg", ftp_w=200, pmax_w=PMAX)
    assert m.format == "mrc" and m.duration_s == e.duration_s == 180
    for t in range(0, 180, 5):
        assert m.target_w_at(t) == pytest.approx(e.target_w_at(t))
        assert m.command_at(t)[0] == pytest.approx(e.command_at(t)[0])
    assert m.target_w_at(180) is None and m.command_at(180)[0] == 0.0
    assert load_workout(DATA / "mrc_smoke.mrc", ftp_w=300, pmax_w=PMAX).target_w_at(130) == pytest.approx(330)
    with pytest.raises(WorkoutError, match=r"mrc_smoke.mrc: line 9: percent-of-FTP value: pass the rider's ftp_w"):
        load_workout(DATA / "mrc_smoke.mrc", pmax_w=PMAX)


def test_erg_percent_values_and_late_start(tmp_path):
    text = ("[COURSE HEADER]\nMINUTES WATTS\n[END COURSE HEADER]\n[COURSE DATA]\n"
            "1.00 150\n2.00 50%  ; half FTP\n2.00 300\n3 300\n[END COURSE DATA]\n")
    with pytest.warns(WorkoutWarning, match=r"p.erg: line 5: the first point is at 1 min; its value holds from 0"):
        w = load_workout(write(tmp_path, text, "p.erg"), ftp_w=200, pmax_w=PMAX)
    check_timeline(w)
    assert w.duration_s == 180
    assert w.target_w_at(30) == 150                               # first point at 1 min holds from 0
    assert w.target_w_at(90) == pytest.approx(125)                # 150 W -> 50 % of 200 W
    assert w.target_w_at(150) == 300
    assert any("holds from 0" in x for x in w.warnings)



def test_erg_written_as_utf16_or_cp1252_is_read(tmp_path):
    # Windows PowerShell 5's '>' (and Notepad's 'Unicode') write UTF-16 with a byte order mark:
    # the file was refused as "binary file (NUL bytes)"; a cp1252 description kept its en dash
    # as a C1 control character (read as latin-1)
    text = (DATA / "erg_smoke.erg").read_text().replace("\n", "\r\n")
    expected = load_workout(DATA / "erg_smoke.erg", ftp_w=200, pmax_w=PMAX)
    for encoding in ("utf-16", "utf-16-be"):
        path = tmp_path / f"{encoding}.erg"
        data = text.encode(encoding)
        path.write_bytes(data if encoding == "utf-16" else b"\xfe\xff" + data)
        w = load_workout(path, ftp_w=200, pmax_w=PMAX)
        assert [(s.start_s, s.target_start_w, s.target_end_w) for s in w.segments] == \
            [(s.start_s, s.target_start_w, s.target_end_w) for s in expected.segments]
    path.write_bytes(b"\xff\xfe" + "[COURSE HEADER]\n".encode("utf-16-le") + b"\x00")
    with pytest.raises(WorkoutError, match="UTF-16 byte order mark but is not UTF-16 text"):
        load_workout(path, ftp_w=200, pmax_w=PMAX)
    path = tmp_path / "cp.erg"
    path.write_bytes(text.replace("DESCRIPTION = ", "DESCRIPTION = Caf\u00e9 \u2013 ").encode("cp1252"))
    assert load_workout(path, ftp_w=200, pmax_w=PMAX).description.startswith("Caf\u00e9 \u2013 ")


def test_a_relative_target_without_an_ftp_says_where_the_rider_gives_it():
    # "pass the rider's ftp_w" named a Python parameter: a rider at ./bike run gives --ftp W
    from fit_files import SWEET_SPOT, fit_workout_bytes
    for data, fmt in ((zwo('<SteadyState Duration="60" Power="0.75"/>'), "zwo"),
                      ((DATA / "mrc_smoke.mrc").read_bytes(), "mrc"), (fit_workout_bytes(SWEET_SPOT), "fit")):
        with pytest.raises(WorkoutError, match=r"\(session\.ftp_w; \./bike run --ftp W\)") as info:
            parse_workout_bytes(data, fmt, source=f"w.{fmt}", pmax_w=PMAX)
        assert str(info.value).count("error:") == 0 and str(info.value).startswith(f"w.{fmt}: ")


def test_run_rides_the_configs_ftp_and_max_heart_rate_when_the_options_are_not_given(tmp_path, capsys):
    """The hint above names session.ftp_w, but ./bike run read the workout with --ftp alone and passed
    ftp 0.0 to the launch file, whose argument replaces the config's parameter: a config with
    session.ftp_w: 250 got "pass the rider's ftp_w (session.ftp_w; ...)", and an .erg with FTP = 200
    rode its watts as written instead of rescaled to 250. The same for session.max_hr_bpm."""
    from bike_plant.config import load_config
    from bike_session import cli
    from fit_files import fit_workout_bytes, heart_rate_step
    cfg = load_config(ROOT / "config" / "bldc_default.yaml")
    cfg["session"] = dict(cfg.get("session") or {}, ftp_w=250.0, max_hr_bpm=200.0)
    path = write(tmp_path, zwo('<SteadyState Duration="60" Power="0.5"/>'), "a.zwo")
    opts = cli.build_parser().parse_args(["run", "--workout", str(path)])
    assert cli._load_workout_for_run(opts, cfg).segments[0].target_start_w == pytest.approx(125.0)
    assert cli._rider_figures(opts, cfg) == (250.0, 200.0)          # what the launch file is given
    opts = cli.build_parser().parse_args(["run", "--workout", str(path), "--ftp", "200", "--max-hr", "180"])
    assert cli._load_workout_for_run(opts, cfg).segments[0].target_start_w == pytest.approx(100.0)
    assert cli._rider_figures(opts, cfg) == (200.0, 180.0)          # the options win
    erg = tmp_path / "erg_smoke.erg"
    erg.write_bytes((DATA / "erg_smoke.erg").read_bytes())
    opts = cli.build_parser().parse_args(["run", "--workout", str(erg)])
    assert "FTP = 200" in erg.read_text()
    assert cli._load_workout_for_run(opts, cfg).segments[0].target_start_w == pytest.approx(100.0 * 250 / 200)
    hr = tmp_path / "hr.fit"
    hr.write_bytes(fit_workout_bytes([heart_rate_step(60, 70, 80)]))
    opts = cli.build_parser().parse_args(["run", "--workout", str(hr)])
    assert cli._load_workout_for_run(opts, cfg).segments[0].heart_rate_bpm == pytest.approx(150.0)
    del cfg["session"]["ftp_w"]
    opts = cli.build_parser().parse_args(["run", "--workout", str(path)])
    assert cli._load_workout_for_run(opts, cfg) is None
    assert "session.ftp_w; ./bike run --ftp W" in capsys.readouterr().err


def test_run_rides_the_configs_session_workout(tmp_path):
    """A config's session.workout is ridden instead of session.profile (the session node's rule), but
    ./bike run passed the launch file's workout "" over it: the config's profile was ridden without a
    word. Now ./bike run reads it, resolved like session.profile against the config's folder (a --set
    copy of the config written elsewhere included): a bad one is one error naming it, nothing starts."""
    import subprocess

    import yaml
    from bike_plant.config import load_config
    from bike_session import cli
    doc = yaml.safe_load((ROOT / "config" / "bldc_default.yaml").read_text())
    params = doc["/**"]["ros__parameters"]
    params["session"].update(profile=str(ROOT / "config" / "profiles" / "demo_intervals.yaml"),
                             workout="w/bad.zwo")
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "bad.zwo").write_text(zwo('<SteadyState Duration="60" Power="0.5"/>'))
    config = tmp_path / "rider.yaml"
    config.write_text(yaml.safe_dump(doc))
    assert cli._config_workout(load_config(config), config) == str(tmp_path / "w" / "bad.zwo")
    for extra in ([], ["--set", "session.period_s=0.1"]):          # the config, and a --set copy of it
        run = subprocess.run([str(ROOT / "bike"), "run", "--config", str(config), "--duration", "0.5", *extra],
                             capture_output=True, text=True, timeout=120)
        errors = [line for line in run.stderr.splitlines() if line.strip()]
        assert run.returncode == 2 and len(errors) == 1, (run.returncode, run.stdout[-2000:], run.stderr[-2000:])
        assert errors[0].startswith(f"error: {tmp_path / 'w' / 'bad.zwo'}: ") and "session.ftp_w" in errors[0]
    params["session"]["ftp_w"] = 200.0
    config.write_text(yaml.safe_dump(doc))
    opts = cli.build_parser().parse_args(["run", "--config", str(config)])
    opts.workout = cli._config_workout(load_config(config), config)
    assert cli._load_workout_for_run(opts, load_config(config)).segments[0].target_start_w == pytest.approx(100.0)


def test_a_replay_rides_the_recorded_commands_not_the_recorded_configs_workout(tmp_path, monkeypatch):
    """A ride of a config's session.workout records that config; its replay writes the recorded
    config with the replay's profile, and ./bike run, which rides a config's session.workout in place
    of its profile, would have ridden the workout file again instead of the recorded Commands."""
    import yaml
    from bike_plant.config import load_config
    from bike_session import cli, replay
    recorded = yaml.safe_load((ROOT / "config" / "bldc_default.yaml").read_text())
    recorded["/**"]["ros__parameters"]["session"]["workout"] = str(DATA / "over_unders.zwo")
    info = {"duration_s": 1.0, "period_s": 0.1, "config_text": yaml.safe_dump(recorded)}
    monkeypatch.setattr(replay, "command_timeline", lambda _bag: ([(0, 0.5, 0, 0.0, None)], info))
    prep = replay.prepare(tmp_path / "session_x", tmp_path / "runs", None, "recorded")
    cfg = load_config(prep["config"])
    assert cfg["session"]["profile"] == str(prep["profile"].resolve())
    assert cli._config_workout(cfg, prep["config"]) is None


@pytest.mark.parametrize("setting, words", [("session.ftp_w=-5", "session.ftp_w: must be in [0, 2000] W"),
                                             ("session.max_hr_bpm=400", "session.max_hr_bpm: must be in [0, 250] bpm")])
def test_a_configs_bad_rider_figure_is_one_error_naming_its_key(tmp_path, setting, words):
    """Now that ./bike run rides the config's FTP and maximum heart rate, a bad one is refused by the
    config check, naming the key, not by the workout reader as its parameter ftp_w / max_hr_bpm."""
    import subprocess
    path = write(tmp_path, zwo('<SteadyState Duration="60" Power="0.5"/>'), "a.zwo")
    run = subprocess.run([str(ROOT / "bike"), "run", "--workout", str(path), "--set", setting, "--duration", "0.5"],
                         capture_output=True, text=True, timeout=120)
    errors = [line for line in run.stderr.splitlines() if line.strip()]
    assert run.returncode == 2 and len(errors) == 1, (run.returncode, run.stdout[-2000:], run.stderr[-2000:])
    assert words in errors[0] and "Traceback" not in run.stderr, errors


@pytest.mark.parametrize("file_name, name", [("C:\\Users\\me\\Workouts\\Sweet Spot.erg", "Sweet Spot"),
                                             ("workouts/Baxter.ERG", "Baxter"), ("Over-unders 2.5", "Over-unders 2.5"),
                                             ("Tempo 3x12.mrc", "Tempo 3x12"), ("", "n")])
def test_erg_file_name_header_names_the_workout(tmp_path, file_name, name):
    # a Windows path was the name whole ("C:\\Users\\...\\Sweet Spot"); a name with a decimal
    # lost what followed its last dot ("Over-unders 2")
    text = (DATA / "erg_smoke.erg").read_text()
    text = re.sub(r"(?m)^FILE NAME = .*$", lambda _m: f"FILE NAME = {file_name}", text)
    assert "FILE NAME = " + file_name in text
    assert load_workout(write(tmp_path, text, "n.erg"), ftp_w=200, pmax_w=PMAX).name == name


def test_a_decimal_comma_is_one_error_that_says_so():
    # a European locale writes '0,75': the error said only "not a number"
    hint = "(numbers take a decimal point, not a comma)"
    erg = ("[COURSE HEADER]\nFTP = {ftp}\nMINUTES WATTS\n[END COURSE HEADER]\n[COURSE DATA]\n"
           "0 {w}\n{t} 100\n[END COURSE DATA]\n")
    for data, fmt, words in (
            (zwo('<SteadyState Duration="60" Power="0,75"/>'), "zwo", "line 2 <SteadyState> attribute Power: "
                                                                      "expected a number, got '0,75'"),
            (zwo('<SteadyState Duration="60,5" Power="0.75"/>'), "zwo", "attribute Duration"),
            (erg.format(ftp=250, w=100, t="1,5"), "erg", "line 7: time is not a number: '1,5'"),
            (erg.format(ftp=250, w="112,5", t=1), "erg", "line 6: watts value is not a number: '112,5'"),
            (erg.format(ftp=250, w="50,5%", t=1), "erg", "line 6: percent value is not a number: '50,5%'"),
            (erg.format(ftp="250,5", w=100, t=1), "erg", "line 2: FTP must be a number of watts")):
        with pytest.raises(WorkoutError) as info:
            parse_workout_bytes(data, fmt, source=f"c.{fmt}", ftp_w=200, pmax_w=PMAX)
        assert words in str(info.value) and str(info.value).endswith(hint), str(info.value)
    with pytest.raises(WorkoutError) as info:
        parse_workout_bytes(zwo('<SteadyState Duration="60" Power="x"/>'), "zwo", ftp_w=200, pmax_w=PMAX)
    assert "comma" not in str(info.value)


@pytest.mark.parametrize("ftp_line", ["FTP =", "FTP = 0", "FTP=  "])
def test_an_erg_ftp_line_without_an_ftp_is_no_ftp(tmp_path, ftp_line):
    # an exporter writing 'FTP = {its FTP}' without one: the file was refused ("FTP must be a number
    # of watts in (0, 2000], got ''") where GoldenCheetah and others ride its watts as written
    text = (DATA / "erg_smoke.erg").read_text().replace("FTP = 200", ftp_line)
    assert ftp_line in text
    with pytest.warns(WorkoutWarning, match=r"e.erg: line 6: 'FTP =( 0)?' names no FTP: the watts are ridden as "
                                            "written"):
        w = load_workout(write(tmp_path, text, "e.erg"), ftp_w=250, pmax_w=PMAX)
    assert w.file_ftp_w is None and w.target_w_at(130) == pytest.approx(220), "not rescaled to the rider's 250 W"
    mrc = (DATA / "mrc_smoke.mrc").read_text().replace("MINUTES PERCENT", ftp_line + "\nMINUTES PERCENT")
    with pytest.warns(WorkoutWarning, match=r"m.mrc: line \d+: 'FTP =( 0)?' names no FTP: the percent take the "
                                            "rider's FTP"):
        assert load_workout(write(tmp_path, mrc, "m.mrc"), ftp_w=250, pmax_w=PMAX).ftp_w == 250
    with pytest.raises(WorkoutError, match=r"line 6: FTP must be a number of watts in \(0, 2000\], got '-5'"):
        load_workout(write(tmp_path, text.replace(ftp_line, "FTP = -5"), "e.erg"), ftp_w=250, pmax_w=PMAX)

def test_yaml_goes_to_the_profile_loader():
    path = ROOT / "config" / "profiles" / "demo_intervals.yaml"
    p = load_workout(path, ftp_w=250, pmax_w=PMAX)
    q = load_profile(path)
    assert type(p) is Profile and p.duration_s == q.duration_s == 60
    assert [p.command_at(t) for t in range(0, 61, 3)] == [q.command_at(t) for t in range(0, 61, 3)]


def test_workout_segment_is_a_segment():
    w = load_workout(DATA / "erg_smoke.erg", ftp_w=200, pmax_w=PMAX)
    s = w.segments[0]
    assert isinstance(s, WorkoutSegment) and s.value_at(60) == pytest.approx(120 / PMAX)


# --------------------------------------------------------------------------- malformed files

BAD_FILES = [
    # (file, where, words)
    ("bad_xml.zwo", "line 6", "<SteadyState> opened at line 4 is not closed"),
    ("unknown_element.zwo", "line 5 <Sprint>", "unknown element <Sprint> in <workout>"),
    ("missing_duration.zwo", "line 4 <SteadyState>", "missing attribute Duration"),
    ("negative_duration.zwo", "line 3 <Ramp> attribute Duration", "must be > 0, got '-60'"),
    ("nonnumeric_power.zwo", "line 3 <IntervalsT> attribute OnPower", "expected a number, got 'high'"),
    ("percent_as_fraction.zwo", "line 3 <SteadyState> attribute Power", "ZWO powers are FTP fractions"),
    ("entity_bomb.zwo", "line 2", "DOCTYPE / entity declarations are not allowed"),
    ("external_entity.zwo", "line 2", "DOCTYPE / entity declarations are not allowed"),
    ("empty.zwo", None, "empty file"),
    ("empty.erg", None, "empty file"),
    ("decreasing.erg", "line 8", "time goes backwards: 1.5 min after 2 min at line 7"),
    ("decreasing.mrc", "line 8", "time goes backwards: 4 min after 5 min at line 7"),
    ("negative_time.mrc", "line 5", "time must be >= 0 minutes"),
    ("nonnumeric.erg", "line 6", "watts value is not a number: '1OO'"),
    ("truncated.erg", "line 8", "missing [END COURSE DATA] (file truncated?)"),
    ("workout.txt", None, "unsupported workout extension '.txt'"),
]


@pytest.mark.parametrize("name,where,words", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_malformed_files(name, where, words):
    path = BAD / name
    with pytest.raises(WorkoutError) as info:
        load_workout(path, ftp_w=250, pmax_w=PMAX)
    msg = str(info.value)
    assert isinstance(info.value, ProfileError)       # the session node's existing except clause catches it
    assert msg.startswith(f"{path}: "), msg
    assert words in msg, msg
    if where:
        assert msg.startswith(f"{path}: {where}: "), msg
        assert info.value.line == int(where.split()[1])


BAD_TEXTS = [
    # (file name, text, where, words)
    ("a.zwo", zwo('<SteadyState Duration="60" Power="0.5"><Bonus/></SteadyState>'), "line 2 <Bonus>",
     "unknown element <Bonus> in <SteadyState>"),
    ("a.zwo", "<workout><SteadyState Duration='1' Power='1'/></workout>", "line 1 <workout>",
     "expected <workout_file>"),
    ("a.zwo", "<workout_file><name>x</name></workout_file>", "line 1 <workout_file>", "missing <workout>"),
    ("a.zwo", zwo(""), "line 1 <workout>", "no blocks"),
    ("a.zwo", zwo('<IntervalsT Repeat="0" OnDuration="1" OffDuration="1" OnPower="1" OffPower="1"/>'),
     "line 2 <IntervalsT> attribute Repeat", "must be in [1, 10000]"),
    ("a.zwo", zwo('<IntervalsT Repeat="2.5" OnDuration="1" OffDuration="1" OnPower="1" OffPower="1"/>'),
     "line 2 <IntervalsT> attribute Repeat", "expected an integer"),
    ("a.zwo", zwo('<IntervalsT Repeat="2" OnDuration="10" OffDuration="5" OnPower="1"/>'),
     "line 2 <IntervalsT>", "missing attribute OffPower (or PowerOffLow/PowerOffHigh)"),
    ("a.zwo", zwo('<IntervalsT Repeat="2" OnDuration="10" OnPower="1" OffPower="1"/>'),
     "line 2 <IntervalsT>", "missing attribute OffDuration"),
    ("a.zwo", zwo('<SteadyState Duration="0" Power="0.5"/>'), "line 2 <SteadyState> attribute Duration", "> 0"),
    ("a.zwo", zwo('<SteadyState Duration="nan" Power="0.5"/>'), "line 2 <SteadyState> attribute Duration",
     "expected a number"),
    ("a.zwo", zwo('<SteadyState Duration="60" Power="-0.5"/>'), "line 2 <SteadyState> attribute Power", ">= 0"),
    ("a.zwo", zwo('<SteadyState Duration="60"/>'), "line 2 <SteadyState>", "missing attribute Power"),
    ("a.zwo", zwo('<SteadyState Duration="60" Power="0.5" power="0.6"/>'), "line 2 <SteadyState> attribute power",
     "attribute given twice"),
    ("a.zwo", zwo('<Warmup Duration="60" PowerLow="0.5" PowerHigh="0.7" Cadence="fast"/>'),
     "line 2 <Warmup> attribute Cadence", "expected a number"),
    ("a.zwo", zwo('<SteadyState Duration="60" Power="0.5" Cadence="5"/>'), "line 2 <SteadyState> attribute Cadence",
     "cadence target 5.0 rpm outside [10, 250]"),
    ("a.zwo", zwo('<SteadyState Duration="60" Power="0.5" Cadence="300"/>'),
     "line 2 <SteadyState> attribute Cadence", "outside [10, 250]"),
    ("a.zwo", zwo('<Warmup Duration="60" Power="0.5"><textevent timeoffset="5"/></Warmup>'),
     "line 2 <textevent>", "missing attribute message"),
    ("a.zwo", zwo('<Warmup Duration="60" Power="0.5"><textevent distoffset="5" message="m"/></Warmup>'),
     "line 2 <textevent> attribute distoffset", "distance-based"),
    ("a.zwo", zwo('<SteadyState Duration="90000" Power="0.5"/>'), "line 2 <SteadyState> attribute Duration",
     "longer than"),
    ("a.zwo", zwo("", head="<sportType>run</sportType>"), "line 1 <sportType>", "not a cycling workout"),
    ("a.zwo", zwo("", head="<durationType>distance</durationType>"), "line 1 <durationType>", "not supported"),
    ("a.zwo", zwo('<SteadyState Duration="60" Power="0.5"/>', head="<ftpOverride>lots</ftpOverride>"),
     "line 1 <ftpOverride>", "expected an FTP"),
    ("a.zwo", "<workout_file>\n<workout>\n<SteadyState Duration='60' Power='0.5'/>\n", "line 4",
     "<workout> opened at line 2 is not closed (file truncated?)"),
    ("a.zwo", "\x00\x01garbage", "line 1", "not well-formed XML"),
    ("a.erg", "0.00 100\n1.00 100\n", "line 1", "unexpected line before [COURSE HEADER]"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n1 100\n[END COURSE DATA]\n[WHAT]\n",
     "line 7", "unknown section [WHAT]"),
    ("a.erg", "[COURSE HEADER]\nMINUTES GRADE\n[END COURSE HEADER]\n", "line 2", "columns 'MINUTES GRADE' are not"),
    ("a.erg", "[COURSE HEADER]\nhello\n[END COURSE HEADER]\n", "line 2", "unrecognised header line"),
    ("a.erg", "[COURSE HEADER]\nFTP = abc\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n1 100\n[END COURSE DATA]\n",
     "line 2", "FTP must be a number"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n[END COURSE DATA]\n", "line 3",
     "at least two points"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n0 200\n[END COURSE DATA]\n", "line 5",
     "no duration"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100 90\n1 100\n[END COURSE DATA]\n", "line 4",
     "expected '<minutes> <watts>'"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 -5\n1 100\n[END COURSE DATA]\n", "line 4",
     "must be >= 0"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n1 100\n[END COURSE DATA]\n0 100\n",
     "line 7", "unexpected line after [END COURSE DATA]"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE HEADER]\n", "line 3", "repeated"),
    ("a.erg", "[COURSE DATA]\n0 100\n", "line 1", "out of place"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 100\n1 100\n[END COURSE DATA]\n"
     "[COURSE TEXT]\nhello\n[END COURSE TEXT]\n", "line 8", "expected '<seconds> <message>"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 1e999\n1 100\n[END COURSE DATA]\n", "line 4",
     "not a number"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0 600%\n1 100\n[END COURSE DATA]\n", "line 4",
     "beyond 500 %"),
    ("a.erg", "[COURSE HEADER]\n[END COURSE HEADER]\n[COURSE DATA]\n0\x00 100\n", None, "binary file"),
    ("a.mrc", "[COURSE HEADER]\nMINUTES WATTS\n[END COURSE HEADER]\n[COURSE DATA]\n0 50\n1 50\n[END COURSE DATA]\n",
     "line 1", "header says MINUTES WATTS"),
    ("a.fit", "whatever", None, "not a FIT file"),
    ("a", "whatever", None, "unsupported workout extension '(none)'"),
]


@pytest.mark.parametrize("name,text,where,words", BAD_TEXTS, ids=[f"bad{i}" for i in range(len(BAD_TEXTS))])
def test_malformed_texts(tmp_path, name, text, where, words):
    path = write(tmp_path, text, name)
    with pytest.raises(WorkoutError) as info:
        load_workout(path, ftp_w=250, pmax_w=PMAX)
    msg = str(info.value)
    assert msg.startswith(f"{path}: "), msg
    assert words in msg, msg
    if where:
        assert msg.startswith(f"{path}: {where}: "), msg


def test_parameter_errors():
    path = DATA / "over_unders.zwo"
    with pytest.raises(WorkoutError, match=r"over_unders.zwo: pmax_w: parameter pmax_w .* is required"):
        load_workout(path, ftp_w=250)
    with pytest.raises(WorkoutError, match=r"over_unders.zwo: line 14 <Warmup> attribute PowerLow: .*ftp_w"):
        load_workout(path, pmax_w=PMAX)
    for kw, words in (({"ftp_w": -1}, "ftp_w must be a number > 0"), ({"ftp_w": math.nan}, "ftp_w"),
                      ({"ftp_w": 5000}, "<= 2000"), ({"pmax_w": 0}, "pmax_w must be"),
                      ({"mode": "sprint"}, "unknown mode 'sprint'"), ({"over_range": "clamp"}, "over_range"),
                      ({"freeride_command": 2}, "freeride_command must be in [0, 1]")):
        args = {"ftp_w": 250, "pmax_w": PMAX, **kw}
        with pytest.raises(WorkoutError, match=None) as info:
            load_workout(path, **args)
        assert str(info.value).startswith(str(path)) and words in str(info.value)


def test_file_errors_and_bounds(tmp_path):
    with pytest.raises(WorkoutError, match="cannot read workout"):
        load_workout(tmp_path / "missing.zwo", ftp_w=250, pmax_w=PMAX)
    folder = tmp_path / "dir.zwo"
    folder.mkdir()
    with pytest.raises(WorkoutError, match="not a regular file"):
        load_workout(folder, ftp_w=250, pmax_w=PMAX)
    # a folder without a suffix was "unsupported workout extension '(none)'"
    with pytest.raises(WorkoutError, match=r"not a regular file \(a directory\)$"):
        load_workout(tmp_path, ftp_w=250, pmax_w=PMAX)
    big = tmp_path / "big.erg"
    big.write_bytes(b";" * (MAX_WORKOUT_BYTES + 1))
    with pytest.raises(WorkoutError, match="too large") as info:
        load_workout(big, ftp_w=250, pmax_w=PMAX)
    assert str(info.value).startswith(str(big))
    many = write(tmp_path, "<workout_file>" + "<a/>" * (MAX_XML_ELEMENTS + 1) + "</workout_file>", "many.zwo")
    with pytest.raises(WorkoutError, match=f"more than {MAX_XML_ELEMENTS} XML elements"):
        load_workout(many, ftp_w=250, pmax_w=PMAX)
    deep = write(tmp_path, "<a>" * (MAX_XML_DEPTH + 1) + "</a>" * (MAX_XML_DEPTH + 1), "deep.zwo")
    with pytest.raises(WorkoutError, match="nested deeper"):
        load_workout(deep, ftp_w=250, pmax_w=PMAX)


def test_expansion_is_bounded():
    block = '<IntervalsT Repeat="10000" OnDuration="0.5" OffDuration="0.5" OnPower="1" OffPower="0.5"/>\n'
    n = MAX_LEAF_SEGMENTS // 20000 + 1
    with pytest.raises(WorkoutError, match=rf"line {n + 1} <IntervalsT> attribute Repeat: .*more than"):
        parse_workout_bytes(zwo(block * n), "zwo", source="x.zwo", ftp_w=200, pmax_w=PMAX)
    with pytest.raises(WorkoutError, match="longer than 24 h"):
        parse_workout_bytes(zwo('<IntervalsT Repeat="10000" OnDuration="10" OffDuration="0" OnPower="1"/>'),
                            "zwo", ftp_w=200, pmax_w=PMAX)
