"""A private DDS domain for one run: claimed with a lock file so that two simulations (or two
test runs) on one host never share a ROS_DOMAIN_ID and ride each other's /clock and commands.

A random pick alone collides (the birthday problem: with 4 concurrent runs over 100 ids,
about 6 %), so each claimed id is held by an flock on /tmp/bike-ros-domains/<id>.lock for
the life of the claiming process (the kernel drops the lock when the process ends, even on
kill -9). An explicit ROS_DOMAIN_ID is always respected and never locked.
"""
from __future__ import annotations

import atexit
import fcntl
import os
import pathlib
import random

LOCK_DIR = pathlib.Path(os.environ.get("BIKE_DOMAIN_LOCK_DIR", "/tmp/bike-ros-domains"))
FIRST_ID = 1
LAST_ID = 200      # Fast DDS ports stay valid up to 232; keep a margin
MAX_ID = 232       # beyond it Fast DDS's ports pass 65535: "Calculated port number is too high"

_held: dict[int, object] = {}      # id -> open lock file (kept open = kept locked)


def claim(first: int = FIRST_ID, last: int = LAST_ID) -> int:
    """Lock and return a domain id no other claimant on this host holds.

    Raises RuntimeError when every id in [first, last] is taken."""
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    ids = list(range(first, last + 1))
    random.SystemRandom().shuffle(ids)
    for domain in ids:
        if domain in _held:
            continue
        f = open(LOCK_DIR / f"{domain}.lock", "a")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _held[domain] = f
        return domain
    raise RuntimeError(f"no free ROS_DOMAIN_ID in {first}..{last}: every one is held by another run "
                       f"(locks in {LOCK_DIR}); set ROS_DOMAIN_ID yourself")


def release(domain: int) -> None:
    """Give a claimed id back (a process that ends releases its ids anyway)."""
    f = _held.pop(domain, None)
    if f is not None:
        f.close()


@atexit.register
def _release_all() -> None:
    """Close the lock files still held at exit (the locks would go with the process anyway;
    closing them here spares the interpreter's ResourceWarning for each open file)."""
    for domain in list(_held):
        release(domain)


def environment_problem() -> str | None:
    """Why the environment's ROS_DOMAIN_ID is no domain a node can join, None when it is one (or
    unset or empty: a private one is claimed). Text ended in an RCLError traceback in every node
    ("ROS_DOMAIN_ID is not an integral number"), an id over MAX_ID in Fast DDS's port error."""
    text = os.environ.get("ROS_DOMAIN_ID", "")
    if not text or (text.isdigit() and int(text) <= MAX_ID):
        return None
    return (f"ROS_DOMAIN_ID {text!r} is not a DDS domain id (a whole number 0..{MAX_ID}): export another, "
            "or unset it for a private one")


def ensure_private_domain(what: str = "run") -> int | None:
    """Set ROS_DOMAIN_ID to a claimed private id unless the user set one; returns the id
    claimed (None when the environment already named one) and says so on stdout."""
    if os.environ.get("ROS_DOMAIN_ID"):
        return None
    domain = claim()
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    print(f"[bike] ROS_DOMAIN_ID={domain} (a private domain for this {what}; "
          "export ROS_DOMAIN_ID to choose one, e.g. to watch with ros2 topic echo)", flush=True)
    return domain
