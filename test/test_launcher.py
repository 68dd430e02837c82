"""The YAML launch subset: parsing, substitutions, conditions, errors, supervision."""
import pathlib
import signal
import sys
import time

import pytest

from bike_session import launcher
from bike_session.launcher import LaunchError, Launcher, NodeSpec, parse_launch

from conftest import LAUNCH_FILE, ros_parameters_of


def write(tmp_path, text):
    path = tmp_path / "x.launch.yaml"
    path.write_text(text)
    return str(path)


def test_project_launch_file_parses_with_and_without_recorder(tmp_path):
    nodes = parse_launch(str(LAUNCH_FILE), {"config": "/abs/c.yaml", "duration": "5.0"})
    assert [n.name for n in nodes] == ["plant", "controller", "session"]
    plant = nodes[0]
    assert plant.shutdown_on_exit and plant.namespace == "bike"
    # the config, then the overrides every node takes after it (none unless `./bike run --ftms`)
    assert plant.params_files[0] == "/abs/c.yaml" and plant.params["duration_s"] == "5.0"
    assert plant.params_files[1].endswith("config/launch/no_overrides.yaml")
    assert pathlib.Path(plant.params_files[1]).is_file()
    args = plant.arguments()
    assert args[:5] == ["--ros-args", "-r", "__node:=plant", "-r", "__ns:=/bike"]
    assert "--params-file" in args and "duration_s:=5.0" in args
    nodes = parse_launch(str(LAUNCH_FILE), {"config": "/c.yaml", "record": "true", "record_dir": str(tmp_path)})
    assert nodes[-1].name == "recorder" and nodes[-1].params["record_dir"] == str(tmp_path)
    nodes = parse_launch(str(LAUNCH_FILE), {"config": "/c.yaml", "ftms": "true", "ftms_port": "0",
                                            "overrides": "/o.yaml"})
    assert nodes[-1].name == "ftms" and nodes[-1].params["ftms.port"] == "0"
    assert all(n.params_files[-1] == "/o.yaml" for n in nodes if n.name in ("plant", "controller"))


def test_a_node_gets_param_values_as_the_launch_files_yaml_reads_them():
    """rcl types an unquoted `-p name:=VALUE` by its own rules: a calibration file or config path
    named y reached the node as true/false (the node refused it for its text parameter), nan / 1e5
    as numbers, and ' #' began a comment. A real rclpy node started with the arguments now gets the
    text as text, all of it, and numbers, true/false and lists as the YAML reading gives them."""
    given = {"calibration_file": "y", "can_log_file": "nan", "a": "1e5", "b": "/tmp/my #1/bike.yaml", "c": "it's",
             "d": "~", "e": "[x", "f": "/tmp/\u00e9", "g": "", "duration_s": "60.0", "h": "0", "i": "true",
             "j": "[1, 2]", "k": 1e-05, "l": True, "m": "09"}
    want = dict(given, duration_s=60.0, h=0, i=True, j=[1, 2])
    spec = NodeSpec(pkg="p", exec="e", name="launched", params=given)
    assert ros_parameters_of(spec.arguments(), given) == want


def test_substitutions_and_conditions(tmp_path, monkeypatch):
    monkeypatch.setenv("BIKE_TEST_VAR", "from-env")
    path = write(tmp_path, """
launch:
- arg: {name: a, default: one}
- arg: {name: b, default: "$(var a)-two"}
- node: {pkg: p, exec: e, name: "$(var b)", namespace: "$(env BIKE_TEST_VAR)", param: [{name: k, value: "$(env NOPE fallback)"}]}
- node: {pkg: p, exec: skipped, if: "false"}
- node: {pkg: p, exec: kept, unless: "false"}
""")
    nodes = parse_launch(path)
    assert [(n.name, n.namespace) for n in nodes] == [("one-two", "from-env"), ("kept", "")]
    assert nodes[0].params == {"k": "fallback"}
    assert parse_launch(path, {"a": "x"})[0].name == "x-two"


@pytest.mark.parametrize("text, message", [
    ("launch: 3", "top-level 'launch:' list"),
    ("launch:\n- node: {exec: e}", "'pkg' is required"),
    ("launch:\n- arg: {name: a}", "has no default"),
    ("launch:\n- node: {pkg: p, exec: e, name: '$(var missing)'}", "unknown launch argument"),
    ("launch:\n- node: {pkg: p, exec: e, if: maybe}", "condition must be true or false"),
    ("launch:\n- include: {file: x}", "unsupported entry 'include'"),
    ("launch: [", "not valid YAML"),
    ("launch: " + "[" * 2000 + "]" * 2000, "nested too deeply"),
    ("launch:\n- node: {pkg: p, exec: e, name: '$(python 1+1)'}", "unsupported substitution"),
])
def test_malformed_launch_files_give_one_clear_error(tmp_path, text, message):
    with pytest.raises(LaunchError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_launch(write(tmp_path, text))


def test_unknown_override_is_an_error(tmp_path):
    with pytest.raises(LaunchError, match="unknown launch argument"):
        parse_launch(write(tmp_path, "launch:\n- arg: {name: a, default: x}\n"), {"b": "1"})


class _Script(NodeSpec):
    """A NodeSpec running a Python snippet instead of a ROS executable."""

    def __init__(self, name, code, shutdown=False):
        super().__init__(pkg="-", exec="-", name=name, shutdown_on_exit=shutdown)
        self.code = code

    def command(self):
        return [sys.executable, "-c", self.code]


# a node that ignores SIGINT and SIGTERM (the launcher has to SIGKILL it); says 'ready' first
STUBBORN = ("import signal, time\nfor s in (signal.SIGINT, signal.SIGTERM): signal.signal(s, signal.SIG_IGN)\n"
            "print('ready', flush=True)\ntime.sleep(60)")


class _Sink:
    """A launcher's stdout that keeps what it was given (the nodes' prefixed lines)."""

    def __init__(self):
        self.lines = []

    def write(self, text):
        self.lines.append(text)

    def flush(self):
        pass

    def text(self) -> str:
        return "".join(self.lines)


def test_launcher_stops_all_when_shutdown_node_exits_and_forwards_sigint(tmp_path):
    marker = tmp_path / "got-sigint"
    waiter = (
        "import signal, sys, time, pathlib\n"
        f"def h(*a):\n    pathlib.Path({str(marker)!r}).write_text('x'); sys.exit(0)\n"
        "signal.signal(signal.SIGINT, h)\nprint('waiting', flush=True)\n"
        "while True: time.sleep(0.05)\n")
    out = _Sink()
    launch = Launcher([_Script("quick", "import time; time.sleep(0.5)", shutdown=True), _Script("waiter", waiter)],
                      stdout=out)
    launch.start()
    start = time.monotonic()
    codes = launch.wait(timeout_s=20)
    assert time.monotonic() - start < 10
    assert codes == {"quick": 0, "waiter": 0}
    assert marker.exists(), "the other node must receive SIGINT, not SIGKILL"
    assert "[waiter] waiting\n" in out.lines


def test_a_line_watcher_says_what_a_nodes_line_tells_and_a_failing_watcher_is_said_not_fatal():
    """./bike run learns from a node's output what only the node knows (the FTMS bridge's port
    when the OS picked it): the watcher's line follows the node's; a watcher that raises is one
    warning and the node's output goes on (a dead pump would leave the node blocked on a full pipe)."""
    out = _Sink()

    def watch(name, line):
        if "boom" in line:
            raise RuntimeError("bad watcher")
        return f"[bike] {name} is on port 4242" if "port 4242" in line else None

    code = "for t in ('listening on port 4242', 'boom', 'after'): print(t, flush=True)"
    launch = Launcher([_Script("talker", code, shutdown=True)], stdout=out, on_line=watch)
    launch.start()
    assert launch.wait(timeout_s=20) == {"talker": 0}
    text = out.text()
    assert "[talker] listening on port 4242\n[bike] talker is on port 4242\n" in text, text
    assert "[launcher] warning: the output watcher failed on a line of 'talker': RuntimeError: bad watcher" in text
    assert text.endswith("[talker] after\n"), text


def test_launcher_escalates_to_sigkill_for_a_node_that_ignores_signals():
    launch = Launcher([_Script("stubborn", STUBBORN)], grace_s=0.5, stdout=open("/dev/null", "w"))
    launch.start()
    time.sleep(0.3)
    codes = launch.shutdown()
    assert codes["stubborn"] == -signal.SIGKILL


def test_a_node_stuck_after_a_normal_end_is_a_warning_but_a_killed_node_fails_the_run(capsys):
    # the run ends by itself (the shutdown node exits 0); the stubborn node is then SIGKILLed
    # (2 s: on a loaded host an interpreter's start-up, before it ignores SIGINT, can take a second)
    launch = Launcher([_Script("plant", "import time; time.sleep(2.0)", shutdown=True), _Script("stubborn", STUBBORN)],
                      grace_s=0.5, stdout=open("/dev/null", "w"))
    launch.start()
    codes = launch.wait(timeout_s=30)
    assert codes["stubborn"] == -signal.SIGKILL and launch.ended_normally
    assert launcher.failed_nodes(launch, codes) == {}
    assert "node 'stubborn' did not stop within 0.5 s of SIGINT after the run ended" in capsys.readouterr().err
    # a node killed from outside mid-run stops the graph and fails it
    launch = Launcher([_Script("plant", "import time; time.sleep(60)", shutdown=True),
                       _Script("victim", "import os, signal, time; time.sleep(0.3); os.kill(os.getpid(), 9)")],
                      grace_s=2.0, stdout=open("/dev/null", "w"))
    launch.start()
    codes = launch.wait(timeout_s=30)
    assert not launch.ended_normally and launcher.failed_nodes(launch, codes) == {"victim": -signal.SIGKILL}


def test_a_node_stuck_after_the_users_ctrl_c_is_named_and_a_warning(capsys):
    """The user stopped the run: it ends as interrupted (the caller's 130), also when a node
    had to be killed on the way out; the launcher says which node, and when."""
    out = _Sink()
    # both say 'ready' once their interpreter runs their code: a SIGINT that lands while Python
    # still starts up ends it with 1, not by the signal (CI under load: the plant's code had not
    # started when the stubborn one was ready)
    launch = Launcher([_Script("plant", "import time; print('ready', flush=True); time.sleep(60)", shutdown=True),
                       _Script("stubborn", STUBBORN)], grace_s=0.5, stdout=out)
    launch.start()
    end = time.monotonic() + 30
    while not {"[stubborn] ready\n", "[plant] ready\n"} <= set(out.lines) and time.monotonic() < end:
        time.sleep(0.05)
    launch.request_stop(signal.SIGINT)
    codes = launch.wait(timeout_s=30)
    assert codes == {"plant": -signal.SIGINT, "stubborn": -signal.SIGKILL} and not launch.ended_normally
    assert launcher.failed_nodes(launch, codes) == {}
    assert "node 'stubborn' did not stop within 0.5 s of SIGINT when the run was stopped; it was stopped with " \
           "SIGKILL" in capsys.readouterr().err
    assert "[launcher] still running 0.5 s after SIGINT: stubborn; stopping with SIGTERM" in out.text()


def test_a_project_node_left_running_after_sigint_prints_its_stacks(ros_domain, monkeypatch):
    """Before the SIGTERM, a project node still running after the SIGINT grace is asked for
    its threads' stacks (SIGUSR1, bike_plant.entry), which come out under its name: where a
    hung node hangs. A real session node, given no grace at all."""
    from conftest import DEFAULT_CONFIG as CONFIG

    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    out = _Sink()
    spec = NodeSpec(pkg="bike_session", exec="session_node", name="session", namespace="bike",
                    params_files=[str(CONFIG)], params={"duration_s": "5.0", "config_path": str(CONFIG)})
    launch = Launcher([spec], grace_s=0.0, stdout=out)
    launch.start()
    end = time.monotonic() + 120
    while "[session] [INFO]" not in out.text() and time.monotonic() < end:
        assert launch.procs["session"].poll() is None, out.text()
        time.sleep(0.05)
    codes = launch.shutdown()
    text = out.text()
    assert "[launcher] still running 0 s after SIGINT: session; stopping with SIGTERM" in text, text
    assert "[session] Current thread" in text or "[session] Thread 0x" in text, text
    assert 'session_node.py", line' in text, text          # the main thread's frames, in the node's code
    assert codes["session"] == 0, text                       # the SIGTERM then stops it on its own path


def test_missing_package_is_a_clear_error():
    with pytest.raises(LaunchError, match="package 'no_such_pkg' not found"):
        launcher.executable_path("no_such_pkg", "x")


def test_launcher_stops_the_graph_when_any_node_fails():
    """A node that exits with an error (e.g. a bad parameter) stops the graph instead of
    leaving the others waiting for it forever."""
    launch = Launcher([_Script("plant", "import time; time.sleep(60)", shutdown=True),
                       _Script("broken", "import sys, time; time.sleep(0.3); sys.exit(2)")],
                      grace_s=2.0, stdout=open("/dev/null", "w"))
    launch.start()
    start = time.monotonic()
    codes = launch.wait(timeout_s=30)
    assert time.monotonic() - start < 10
    assert codes["broken"] == 2 and codes["plant"] != 0


def test_an_interrupted_node_import_ends_with_exit_130_and_no_traceback(tmp_path):
    """bike_plant.entry.start: a Ctrl-C while a node module is still importing (rclpy, numba,
    kernels: 1-3 s at the start of ./bike run) ends the process quietly with 130. (The console
    script's own few lines before it are not covered: a traceback stays possible in the
    first ~0.1 s.)"""
    import subprocess

    (tmp_path / "slow_node_module.py").write_text("raise KeyboardInterrupt  # as if SIGINT came mid-import\n")
    code = f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from bike_plant.entry import start; start('slow_node_module')"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 130, run
    assert "Traceback" not in run.stderr + run.stdout and "KeyboardInterrupt" not in run.stderr, run.stderr


def test_a_node_whose_main_returned_exits_with_its_code_and_all_its_output_without_finalising(tmp_path):
    """bike_plant.entry.start: once a node's main() has returned (the node shut itself down),
    the process ends with main()'s exit code at once: the interpreter's finalisation (its
    garbage collection of the kernels took seconds per node at the end of a run) does not run,
    as an atexit handler shows, while what the node wrote, in Python's buffers and C's (an
    rcutils log line), still comes out whole on the pipe."""
    import subprocess

    (tmp_path / "finished_node_module.py").write_text(
        "import atexit, ctypes, sys\n"
        "atexit.register(lambda: print('finalised', file=sys.stderr, flush=True))\n"
        "def main():\n"
        "    sys.stdout.write('bag closed' + 5000 * '.')  # no newline: still in the buffer\n"
        "    ctypes.CDLL(None).printf(b'from C without a newline')\n"
        "    return 3\n")
    code = (f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from bike_plant.entry import start; "
            f"sys.exit(start('finished_node_module'))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 3, run
    assert run.stdout == "bag closed" + 5000 * "." + "from C without a newline" or \
        run.stdout == "from C without a newline" + "bag closed" + 5000 * ".", run.stdout[-200:]
    assert "finalised" not in run.stderr and "Traceback" not in run.stderr, run.stderr


def _ctrl_c_bike_run(tmp_path, started, args, env=None):
    """`./bike run` (60 s) with its output in a file; SIGINT once every string of ``started``
    is in it. Returns (output, exit code)."""
    import os
    import pathlib
    import random
    import subprocess

    root = pathlib.Path(__file__).resolve().parents[1]
    out = tmp_path / "run.log"
    with open(out, "w") as fh:
        proc = subprocess.Popen([str(root / "bike"), "run", "--duration", "60", *args],
                                stdout=fh, stderr=subprocess.STDOUT,
                                env=dict(os.environ, ROS_DOMAIN_ID=str(random.randint(101, 200)), **(env or {})))
        try:
            # a cold numba cache (the 3.12 leg's first graph) compiles plant and controller at once:
            # 50 s and more on a loaded 2-core machine
            end = time.monotonic() + 180
            while time.monotonic() < end and not all(tag in out.read_text() for tag in started):
                assert proc.poll() is None, out.read_text()[-3000:]
                time.sleep(0.1)
            proc.send_signal(signal.SIGINT)
            code = proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
    return out.read_text(), code


def test_ctrl_c_of_a_started_graph_stops_every_node_without_a_traceback(tmp_path):
    """Ctrl-C on `./bike run` once every node runs its main(): each stops on its own SIGINT
    path, the run ends at once with code 130 (interrupted, not finished), says so, and no
    node prints a traceback."""
    # the nodes' first lines after their warm-up (a Ctrl-C during it: the next test)
    started = ("[plant] [INFO]", "bike.plant]: plant: backend=", "bike.controller]: controller: sync_mode=",
               "[session] [INFO]")
    text, code = _ctrl_c_bike_run(tmp_path, started, ["--record", str(tmp_path / "rec")])
    assert all(tag in text for tag in started), text[-3000:]
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-3000:]
    assert code == 130, text[-3000:]
    assert "[launcher] interrupted by SIGINT: every node was stopped" in text, text[-3000:]
    assert "exited with code" not in text and "was killed by" not in text, text[-3000:]
    assert "did not stop within" not in text and "still running" not in text, text[-3000:]
    # the recording up to the stop is closed and summarised
    bags = [b for b in (tmp_path / "rec").iterdir() if b.is_dir()]
    assert len(bags) == 1 and (bags[0] / "metadata.yaml").exists(), text[-3000:]
    assert f"[bike] bag written: {bags[0]}" in text and "mean braking power" in text.lower(), text[-3000:]


def test_ctrl_c_during_the_first_compile_stops_every_node_without_a_traceback(tmp_path):
    """Ctrl-C while the plant and the controller compile their kernels (an empty numba cache:
    the first run after an install): the run stops at once with 130. CI (3.12) saw a SIGINT
    land in llvmlite's ctypes callback, where it was printed as a traceback and swallowed;
    the node then logged a failed warm-up and ran on, and the run took 10 s to end."""
    started = ("bike.plant]: compiling the numba kernels", "bike.controller]: compiling the numba kernels")
    text, code = _ctrl_c_bike_run(tmp_path, started, [], env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    assert all(tag in text for tag in started), text[-3000:]
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-3000:]
    assert "warm-up failed" not in text and "kernels ready" not in text, text[-3000:]
    # neither node went on to its run
    assert "plant: backend=" not in text and "controller: sync_mode=" not in text, text[-3000:]
    assert code == 130 and "[launcher] interrupted by SIGINT: every node was stopped" in text, text[-3000:]
    assert "exited with code" not in text and "was killed by" not in text, text[-3000:]
