"""tools/dds_restart_probe.py: plain rclpy writers survive while a reader process is killed with
SIGKILL and restarted; each restart must hear every surviving writer. This is the middleware
premise of the kill -9 recovery tests, checked without the bike's nodes (README, reliability
table: a realtime controller that gets no Command)."""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest
from node_harness import domain, tool_module  # noqa: F401

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROBE = ROOT / "tools" / "dds_restart_probe.py"


def _probe(domain, *args):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.run([sys.executable, str(PROBE), *args], env=env, capture_output=True, text=True,
                          timeout=240)


@pytest.mark.faults
def test_a_reader_restarted_after_kill_9_hears_every_surviving_writer(domain):
    run = _probe(domain, "--restarts", "4", "--peers", "4", "--seed", "1")
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "dds restart probe: 0 of 4 restarts deaf" in run.stdout, run.stdout
    # under LOCALHOST rmw_fastrtps always adds shared memory; the summary says so
    assert "transports SHM + UDPv4 (rmw_fastrtps for LOCALHOST)" in run.stdout, run.stdout


def test_the_probe_names_the_transports_in_effect():
    """FASTDDS_BUILTIN_TRANSPORTS counts only outside LOCALHOST (a UDPv4-only run under
    LOCALHOST, believed in an earlier stop, still went over shared memory)."""
    probe = tool_module("dds_restart_probe")
    udp = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
    assert probe.transports_in_effect(dict(udp, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")).startswith("SHM + UDPv4")
    assert probe.transports_in_effect(dict(udp, ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")) == "UDPv4"
    assert probe.transports_in_effect({}) == "DEFAULT (SHM + UDPv4)"


@pytest.mark.faults
def test_the_probe_reports_a_writer_it_never_hears(domain):
    """The probe's own check: a topic nobody writes counts as deaf, with its name, and the exit
    status says so (a probe that could not see deafness would pass the test above for nothing)."""
    run = _probe(domain, "--restarts", "1", "--peers", "1", "--silent-topic", "--wait-s", "2", "--give-up-s", "2")
    assert run.returncode == 1, run.stdout + run.stderr[-3000:]
    assert "never within 2 s: ['probe_nobody']" in run.stdout, run.stdout
    assert "1 of 1 restarts deaf" in run.stdout, run.stdout


@pytest.mark.faults
def test_the_realtime_controllers_reader_restarted_after_kill_9_hears_every_writer(domain):
    """The same with the realtime controller's side of it: a best-effort reader of reliable
    writers sending PlantState-sized messages (--best-effort, --payload-bytes, --rates-hz)."""
    run = _probe(domain, "--restarts", "2", "--peers", "2", "--seed", "2", "--best-effort",
                 "--payload-bytes", "600", "--rates-hz", "1000")
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "0 of 2 restarts deaf" in run.stdout, run.stdout
    assert "2 peers at 1000 Hz, 600 B messages, best-effort reader" in run.stdout, run.stdout
