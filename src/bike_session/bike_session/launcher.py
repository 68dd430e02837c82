"""A small process launcher for ROS 2 YAML launch descriptions.

The `launch` / `ros2 launch` tools are not on PyPI (ROS2_ON_PIP.md), so the node graph is
started here from the same declarative file that `ros2 launch` reads on a full ROS 2
install. Supported subset of the YAML launch format:

- ``arg`` (name, default), overridable from the caller;
- ``node`` (pkg, exec, name, namespace, param: [{from: FILE} | {name, value}],
  ros_args, if / unless, on_exit: shutdown);
- ``executable`` (cmd, args, name, cwd, env: [{name, value}], if / unless, on_exit:
  shutdown): any program, e.g. the drive emulator. ``cmd`` (+ ``args``) is split into
  words like a shell would (shlex) but never run through a shell; a first word without a
  slash is looked up on PATH;
- substitutions ``$(var NAME)``, ``$(env NAME [DEFAULT])``, ``$(find-pkg-share PKG)``,
  ``$(find-pkg-prefix PKG)``.

Every node is a separate OS process in its own process group. On Ctrl-C / SIGTERM, or
when a node marked ``on_exit: shutdown`` ends, the others get SIGINT, then SIGTERM and
SIGKILL if they do not stop in time. Nothing in the file is evaluated as code.
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

from bike_plant.config import YamlFileError, parse_yaml_text, ros_param_text

_SUBST = re.compile(r"\$\(([a-z-]+)((?:\s+[^()\s]+)*)\s*\)")
TRUE_WORDS = {"true", "1", "yes", "on"}
FALSE_WORDS = {"false", "0", "no", "off", ""}


class LaunchError(ValueError):
    """The launch description is malformed or names something that does not exist."""


@dataclass
class NodeSpec:
    pkg: str
    exec: str
    name: str
    namespace: str = ""
    params_files: list[str] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)
    ros_args: list[str] = field(default_factory=list)
    shutdown_on_exit: bool = False

    def command(self) -> list[str]:
        return [executable_path(self.pkg, self.exec)] + self.arguments()

    def popen_kwargs(self) -> dict:
        return {}

    def arguments(self) -> list[str]:
        args = ["--ros-args", "-r", f"__node:={self.name}"]
        if self.namespace:
            args += ["-r", f"__ns:=/{self.namespace.strip('/')}"]
        for path in self.params_files:
            args += ["--params-file", path]
        for key, value in self.params.items():
            args += ["-p", f"{key}:={ros_param_value(value)}"]
        return args + list(self.ros_args)


def ros_param_value(value) -> str:
    """The text of ``-p name:=VALUE`` for a launch file's param value: a number, true/false or a
    list when its YAML reading is one (yaml.safe_load, as this project's loader reads a config and
    ros2 launch guesses a substituted value's type), else the text given, all of it, quoted so
    that rcl reads it as text. rcl types an unquoted value by its own rules: a --calibration file
    or a path named y reached the node as true/false, nan or 1e5 as a number, and ' #' began a
    comment (a config path '/tmp/my #1/bike.yaml' reached the node as '/tmp/my')."""
    if isinstance(value, str):
        typed = typed_value(value)
        value = value if typed is None else typed
    return ros_param_text(value)


def typed_value(text: str):
    """The number, true/false or list a launch file's param value ``text`` is to its YAML reading,
    None when it is text (the node gets it as text, all of it)."""
    try:
        parsed = parse_yaml_text(text)
    except YamlFileError:
        return None             # not YAML (an unclosed '['): text
    return parsed if isinstance(parsed, (bool, int, float, list)) else None


# the project's nodes print every thread's Python stack on SIGUSR1 and run on
# (bike_plant.entry.start); any other program may die of it or use it (the drive emulator
# injects a fault), so only these get it
STACKS_ON_SIGUSR1 = {("bike_plant", "plant_node"), ("bike_controller", "controller_node"),
                     ("bike_session", "session_node"), ("bike_session", "recorder_node"),
                     ("bike_session", "ftms_node")}
STACKS_WAIT_S = 0.5


@dataclass
class ExecutableSpec:
    """An ``executable`` action: a program with its arguments (no ROS arguments added)."""
    name: str
    argv: list[str]
    cwd: str | None = None
    env: dict[str, str] = field(default_factory=dict)
    shutdown_on_exit: bool = False

    def command(self) -> list[str]:
        program = self.argv[0]
        if os.sep not in program:
            found = shutil.which(program)
            if found is None:
                raise LaunchError(f"executable '{program}' not found on PATH")
            program = found
        elif not os.access(program, os.X_OK):
            raise LaunchError(f"executable '{program}' not found or not executable")
        return [program] + self.argv[1:]

    def popen_kwargs(self) -> dict:
        kwargs = {}
        if self.cwd:
            kwargs["cwd"] = self.cwd
        if self.env:
            kwargs["env"] = dict(os.environ, **self.env)
        return kwargs


def _executable(body: dict, args: dict[str, str], where: str) -> ExecutableSpec:
    if not isinstance(body.get("cmd"), str) or not body["cmd"].strip():
        raise LaunchError(f"{where}.executable: 'cmd' is required")
    try:
        argv = shlex.split(_substitute(body["cmd"], args))
        extra = body.get("args", "")
        if extra:
            argv += shlex.split(_substitute(str(extra), args))
    except ValueError as exc:
        raise LaunchError(f"{where}.executable: cannot split the command line ({exc})") from None
    if not argv:
        raise LaunchError(f"{where}.executable: 'cmd' is empty after substitution")
    env = {}
    for eindex, item in enumerate(body.get("env", []) or []):
        if not isinstance(item, dict) or "name" not in item or "value" not in item:
            raise LaunchError(f"{where}.executable.env[{eindex}]: needs 'name' and 'value'")
        env[str(item["name"])] = _substitute(str(item["value"]), args)
    cwd = _substitute(body["cwd"], args) if body.get("cwd") else None
    name = _substitute(body.get("name") or os.path.basename(argv[0]), args)
    return ExecutableSpec(name=name, argv=argv, cwd=cwd, env=env, shutdown_on_exit=body.get("on_exit") == "shutdown")


def executable_path(pkg: str, exe: str) -> str:
    """Where `ros2 run PKG EXE` looks: <prefix>/lib/<pkg>/<exe>."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        prefix = get_package_prefix(pkg)
    except PackageNotFoundError:
        raise LaunchError(f"package '{pkg}' not found (is the workspace built and sourced?)") from None
    path = os.path.join(prefix, "lib", pkg, exe)
    if not os.access(path, os.X_OK):
        raise LaunchError(f"executable '{exe}' of package '{pkg}' not found at {path}")
    return path


def _substitute(text, args: dict[str, str]) -> str:
    if not isinstance(text, str):
        return text if not isinstance(text, bool) else str(text).lower()

    def repl(match: re.Match) -> str:
        kind, rest = match.group(1), match.group(2).split()
        if kind == "var":
            if len(rest) != 1 or rest[0] not in args:
                raise LaunchError(f"unknown launch argument in {match.group(0)}")
            return args[rest[0]]
        if kind == "env":
            if not rest:
                raise LaunchError(f"{match.group(0)} needs a variable name")
            return os.environ.get(rest[0], rest[1] if len(rest) > 1 else "")
        if kind in ("find-pkg-share", "find-pkg-prefix"):
            from ament_index_python.packages import (PackageNotFoundError, get_package_prefix,
                                                     get_package_share_directory)
            try:
                return get_package_share_directory(rest[0]) if kind == "find-pkg-share" else get_package_prefix(rest[0])
            except (PackageNotFoundError, IndexError):
                raise LaunchError(f"{match.group(0)}: package not found") from None
        raise LaunchError(f"unsupported substitution {match.group(0)}")

    return _SUBST.sub(repl, text)


def _truth(value: str, where: str) -> bool:
    word = str(value).strip().lower()
    if word in TRUE_WORDS:
        return True
    if word in FALSE_WORDS:
        return False
    raise LaunchError(f"{where}: condition must be true or false, got {value!r}")


def parse_launch(path: str, overrides: dict[str, str] | None = None) -> list[NodeSpec | ExecutableSpec]:
    """Read a YAML launch file; return the nodes to start (conditions applied)."""
    try:
        with open(path) as stream:
            doc = parse_yaml_text(stream.read())
    except OSError as exc:
        raise LaunchError(f"{path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise LaunchError(f"{path}: not a text file") from None
    except YamlFileError as exc:
        raise LaunchError(f"{path}: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("launch"), list):
        raise LaunchError(f"{path}: expected a top-level 'launch:' list")
    overrides = dict(overrides or {})
    args: dict[str, str] = {}
    nodes: list[NodeSpec | ExecutableSpec] = []
    for index, entry in enumerate(doc["launch"]):
        where = f"{path}: launch[{index}]"
        if not isinstance(entry, dict) or len(entry) != 1:
            raise LaunchError(f"{where}: each entry is a mapping with one key (arg, node or executable)")
        kind, body = next(iter(entry.items()))
        if not isinstance(body, dict):
            raise LaunchError(f"{where}.{kind}: expected a mapping")
        if kind == "arg":
            name = body.get("name")
            if not isinstance(name, str):
                raise LaunchError(f"{where}.arg: needs a name")
            if name in overrides:
                args[name] = str(overrides.pop(name))
            elif "default" in body:
                args[name] = _substitute(str(body["default"]) if not isinstance(body["default"], bool)
                                         else str(body["default"]).lower(), args)
            else:
                raise LaunchError(f"{where}.arg: argument '{name}' has no default and was not given")
        elif kind in ("node", "executable"):
            if "if" in body and not _truth(_substitute(body["if"], args), where):
                continue
            if "unless" in body and _truth(_substitute(body["unless"], args), where):
                continue
            if kind == "executable":
                nodes.append(_executable(body, args, where))
                continue
            for key in ("pkg", "exec"):
                if not isinstance(body.get(key), str):
                    raise LaunchError(f"{where}.node: '{key}' is required")
            spec = NodeSpec(pkg=body["pkg"], exec=body["exec"],
                            name=_substitute(body.get("name", body["exec"]), args),
                            namespace=_substitute(body.get("namespace", ""), args),
                            shutdown_on_exit=body.get("on_exit") == "shutdown")
            for pindex, param in enumerate(body.get("param", []) or []):
                if not isinstance(param, dict):
                    raise LaunchError(f"{where}.node.param[{pindex}]: expected a mapping")
                if "from" in param:
                    spec.params_files.append(_substitute(param["from"], args))
                elif "name" in param and "value" in param:
                    spec.params[param["name"]] = _substitute(param["value"], args)
                else:
                    raise LaunchError(f"{where}.node.param[{pindex}]: needs 'from' or 'name' + 'value'")
            ros_args = body.get("ros_args", "")
            spec.ros_args = _substitute(ros_args, args).split() if ros_args else []
            nodes.append(spec)
        else:
            raise LaunchError(f"{where}: unsupported entry '{kind}' (supported: arg, node, executable)")
    if overrides:
        raise LaunchError(f"{path}: unknown launch argument(s): {', '.join(sorted(overrides))}")
    return nodes


class Launcher:
    """Starts NodeSpecs as processes and supervises them."""

    def __init__(self, nodes: list[NodeSpec | ExecutableSpec], *, prefix_output: bool = True, grace_s: float = 10.0,
                 stdout=None, on_line: Callable[[str, str], str | None] | None = None):
        self.nodes = nodes
        # on_line(node name, line): a line of the caller's own to print after it, or None. How
        # ./bike run learns what only a node knows (the FTMS bridge's port when the OS picked it)
        self.on_line = on_line
        self.prefix_output = prefix_output
        self.grace_s = grace_s
        self.ended_normally = False      # wait(): the graph ended by itself, every node so far with 0
        self.escalated: dict[str, int] = {}   # shutdown(): nodes that needed SIGTERM / SIGKILL
        self.stdout = stdout or sys.stdout
        self.procs: dict[str, subprocess.Popen] = {}
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.stopped_by_signal: int | None = None   # request_stop() from a signal handler: which one

    def start(self) -> None:
        commands = [spec.command() for spec in self.nodes]     # every program found before any starts
        for spec, command in zip(self.nodes, commands):
            proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True, text=True, bufsize=1,
                                    **spec.popen_kwargs())
            self.procs[spec.name] = proc
            thread = threading.Thread(target=self._pump, args=(spec.name, proc), daemon=True)
            thread.start()
            self._threads.append(thread)

    def _pump(self, name: str, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            said = self._watch(name, line)
            with self._lock:
                self.stdout.write(f"[{name}] {line}" if self.prefix_output else line)
                if said:
                    self.stdout.write(said.rstrip("\n") + "\n")
                self.stdout.flush()

    def _watch(self, name: str, line: str) -> str | None:
        if self.on_line is None:
            return None
        try:
            return self.on_line(name, line)
        except Exception as exc:  # noqa: BLE001 - a dead pump leaves the node blocked on a full pipe
            return f"[launcher] warning: the output watcher failed on a line of '{name}': {type(exc).__name__}: {exc}"

    def request_stop(self, signum: int | None = None, _frame=None) -> None:
        if signum is not None and self.stopped_by_signal is None:
            self.stopped_by_signal = int(signum)
        self._stop.set()

    def wait(self, timeout_s: float | None = None) -> dict[str, int]:
        """Run until a shutdown node exits, any node fails (exit code != 0), every node
        exits, a signal, or the timeout: a graph missing a node would otherwise wait forever."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        shutdown_names = {spec.name for spec in self.nodes if spec.shutdown_on_exit}
        self.ended_normally = False
        while not self._stop.is_set():
            codes = {name: proc.poll() for name, proc in self.procs.items()}
            if all(code is not None for code in codes.values()):
                self.ended_normally = all(code == 0 for code in codes.values())
                break
            if any(codes[name] is not None for name in shutdown_names):
                self.ended_normally = all(codes[name] in (None, 0) for name in codes)
                break
            if any(code not in (None, 0) for code in codes.values()):
                break                       # a node failed (its error is on the output): stop the graph
            if deadline is not None and time.monotonic() > deadline:
                break
            time.sleep(0.05)
        return self.shutdown()

    def shutdown(self) -> dict[str, int]:
        """SIGINT every running node, then SIGTERM, then SIGKILL; return exit codes. A node
        still running after the SIGINT grace first prints its threads' stacks (the project's
        nodes do on SIGUSR1), so that the output shows where it hung."""
        for sig, wait_s in ((signal.SIGINT, self.grace_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
            running = [p for p in self.procs.values() if p.poll() is None]
            if not running:
                break
            if sig != signal.SIGINT:
                self.escalated.update({name: sig for name, p in self.procs.items() if p in running})
            if sig == signal.SIGTERM:
                self._print_stacks(running)
            for proc in running:
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    pass
            end = time.monotonic() + wait_s
            while time.monotonic() < end and any(p.poll() is None for p in running):
                time.sleep(0.05)
        for thread in self._threads:
            thread.join(timeout=1.0)
        return {name: proc.wait() for name, proc in self.procs.items()}

    def _print_stacks(self, stuck: list[subprocess.Popen]) -> None:
        specs = {spec.name: spec for spec in self.nodes}
        names = [name for name, p in self.procs.items() if p in stuck]
        with self._lock:
            self.stdout.write(f"[launcher] still running {self.grace_s:g} s after SIGINT: {', '.join(names)}; "
                              f"stopping with SIGTERM (their stacks follow, where they print them)\n")
            self.stdout.flush()
        asked = False
        for name in names:
            spec = specs.get(name)
            if isinstance(spec, NodeSpec) and (spec.pkg, spec.exec) in STACKS_ON_SIGUSR1:
                try:
                    os.kill(self.procs[name].pid, signal.SIGUSR1)
                    asked = True
                except ProcessLookupError:
                    pass
        if asked:
            time.sleep(STACKS_WAIT_S)        # the pump threads relay what faulthandler wrote


def failed_nodes(launcher: Launcher, codes: dict[str, int]) -> dict[str, int]:
    """The nodes whose exit code fails the run. After a run that ended by itself (every
    result in) or that the user stopped (Ctrl-C, SIGTERM: the run ends as interrupted either
    way), a node that would not stop on SIGINT and had to be stopped with SIGTERM / SIGKILL
    (e.g. a DDS flush stuck on a loaded machine) gets a warning, not a failed run; its stacks
    are in the output (Launcher.shutdown)."""
    bad = {name: code for name, code in codes.items() if code not in (0, -signal.SIGINT, 130)}
    if launcher.ended_normally or launcher.stopped_by_signal is not None:
        when = "after the run ended" if launcher.ended_normally else "when the run was stopped"
        for name in [n for n in bad if n in launcher.escalated and bad[n] == -launcher.escalated[n]]:
            print(f"[launcher] warning: node '{name}' did not stop within {launcher.grace_s:g} s of SIGINT {when}; "
                  f"it was stopped with {signal.Signals(launcher.escalated[name]).name}", file=sys.stderr)
            del bad[name]
    return bad


def run(launch_file: str, args: dict[str, str] | None = None, timeout_s: float | None = None,
        on_line: Callable[[str, str], str | None] | None = None) -> int:
    """Launch, supervise and stop the graph; returns 0 when every node ended cleanly, 1 when
    one failed, and 128 + the signal's number when the user stopped the run (Ctrl-C: 130,
    SIGTERM: 143; a shell or CI job must not take an interrupted session for a finished one).
    ``on_line``: see :class:`Launcher`."""
    launcher = Launcher(parse_launch(launch_file, args), on_line=on_line)
    previous = {sig: signal.signal(sig, launcher.request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        launcher.start()
        codes = launcher.wait(timeout_s)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    bad = failed_nodes(launcher, codes)
    for name, code in bad.items():
        if code < 0:
            try:
                how = f"was killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"was killed by signal {-code}"
            print(f"[launcher] node '{name}' {how}: the run was stopped",
                  file=sys.stderr)
        else:
            print(f"[launcher] node '{name}' exited with code {code}", file=sys.stderr)
    if bad:
        return 1
    if launcher.stopped_by_signal is not None:
        print(f"[launcher] interrupted by {signal.Signals(launcher.stopped_by_signal).name}: every node was "
              f"stopped", file=sys.stderr)
        return 128 + launcher.stopped_by_signal
    return 0
