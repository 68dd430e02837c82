"""Private DDS domains (bike_session.domains): two runs on one host never share an id."""
import os
import subprocess
import sys

import pytest

from bike_session import domains


def test_claimed_ids_are_unique_across_processes_and_freed_on_exit(tmp_path, monkeypatch):
    monkeypatch.setattr(domains, "LOCK_DIR", tmp_path)
    # a lock directory of its own: ids this process holds in the real one (an earlier test's
    # claim) must not count here
    monkeypatch.setattr(domains, "_held", {})
    held = [domains.claim(1, 6) for _ in range(3)]
    assert len(set(held)) == 3
    # another process gets only the other three ids, then nothing
    code = ("import pathlib, sys; from bike_session import domains; domains.LOCK_DIR = pathlib.Path(sys.argv[1]); "
            "got = [domains.claim(1, 6) for _ in range(3)]; print(*got)\n"
            "try:\n    domains.claim(1, 6)\nexcept RuntimeError as e:\n    print('full:', e)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, check=True).stdout
    others = {int(x) for x in out.splitlines()[0].split()}
    assert others == set(range(1, 7)) - set(held)
    assert "full: no free ROS_DOMAIN_ID in 1..6" in out
    # the child ended: its locks are gone; releasing ours frees those too
    domains.release(held[0])
    again = {domains.claim(1, 6) for _ in range(4)}
    assert held[0] in again and not (again & set(held[1:]))


def test_an_explicit_domain_is_respected(monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert domains.ensure_private_domain() is None and os.environ["ROS_DOMAIN_ID"] == "42"
    monkeypatch.delenv("ROS_DOMAIN_ID")
    d = domains.ensure_private_domain()
    assert os.environ["ROS_DOMAIN_ID"] == str(d)
    domains.release(d)
    with pytest.raises(RuntimeError):
        domains.claim(5, 4)


@pytest.mark.parametrize("value, good", [("", True), ("0", True), ("232", True), ("abc", False), (" 5", False),
                                         ("233", False), ("-1", False), ("1e2", False)])
def test_a_domain_id_the_nodes_cannot_join_is_one_error_before_they_start(value, good, monkeypatch):
    """ROS_DOMAIN_ID=abc ended in an RCLError traceback in every node ('not an integral number'),
    999 in Fast DDS's 'Calculated port number is too high' from each: ./bike run, replay, fleet
    and bench refuse it in one line first (shift too, without --domain)."""
    from bike_session import cli
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    assert (domains.environment_problem() is None) == good
    if not good:
        run = subprocess.run([sys.executable, "-m", "bike_session.cli", "run", "--duration", "1"], capture_output=True,
                             text=True, timeout=60, env=dict(os.environ, ROS_DOMAIN_ID=value))
        lines = [line for line in run.stderr.splitlines() if line.strip()]
        assert run.returncode == 2 and run.stdout == "" and lines == [f"error: {domains.environment_problem()}"]
        for argv in (["replay", "no_bag"], ["fleet", "--graph", "1"], ["bench", "--only", "graph"], ["shift", "1"]):
            assert cli.main(argv) == 2, argv


def test_a_claiming_process_exits_without_resource_warnings(tmp_path):
    """The held lock files are closed at exit (the CI log had one ResourceWarning per id)."""
    code = ("import pathlib, sys; from bike_session import domains; domains.LOCK_DIR = pathlib.Path(sys.argv[1]); "
            "print(domains.claim(1, 6), domains.claim(1, 6))")
    run = subprocess.run([sys.executable, "-X", "dev", "-c", code, str(tmp_path)], capture_output=True, text=True,
                         check=True)
    assert len(run.stdout.split()) == 2
    assert "ResourceWarning" not in run.stderr, run.stderr
