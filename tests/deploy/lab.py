"""The netns lab for tests: hosts in network namespaces on this machine (deploy/netns-lab.sh).

A :class:`Lab` brings the script's lab up under a prefix of its own, hands out its :class:`Host`
objects, and on the way out stops every process it started there and takes the lab down. Run
as root with iproute2 (CI does); :func:`unavailable` says why not otherwise.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "deploy" / "netns-lab.sh"

#: A test lab's prefix is this, the pid of the pytest that made it and a random tag: two
#: sessions never share a lab, and one left by a killed session is found and removed
#: (reap_orphan_labs) by the next.
PREFIX_ROOT = "rtlab"
ORPHAN = re.compile(rf"^({PREFIX_ROOT}(\d+)-[0-9a-f]{{4}})-(br|h\d+|n\d+)$")

SCRIPT_TIMEOUT_S = 60.0  # a bound on one call of the script, which takes milliseconds
STOP_S = 5.0  # how long a process gets to exit after SIGTERM, before SIGKILL


class LabError(RuntimeError):
    """The lab script failed."""


def unavailable() -> str | None:
    """Why no lab can be made here, or None when one can."""
    if os.geteuid() != 0:
        return "the netns lab needs root to create network namespaces (CI runs as root)"
    if shutil.which("ip") is None:
        return "the netns lab needs 'ip': apt-get install iproute2"
    probe = f"{PREFIX_ROOT}-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], check=False, capture_output=True, text=True)
    if made.returncode:  # root without CAP_SYS_ADMIN, as in an unprivileged container
        return f"cannot create a network namespace here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], check=True)
    return None


def partitions_unavailable(path: str | None = None) -> str | None:
    """Why a lab's hosts cannot be partitioned here (the script's partition needs nftables), or
    None when they can; ``path``: the PATH to look in (this process's when None)."""
    if shutil.which("nft", path=path) is None:
        return "partitions need nftables ('nft' not on PATH): apt-get install nftables (.ci/run installs it)"
    return None


def unique_prefix() -> str:
    return f"{PREFIX_ROOT}{os.getpid()}-{secrets.token_hex(2)}"


def namespaces() -> list[str]:
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout
    return [line.split()[0] for line in listed.splitlines() if line.strip()]


def reap_orphan_labs() -> list[str]:
    """Take down the test labs whose pytest is gone (killed before its teardown); their prefixes."""
    orphans = set()
    for name in namespaces():
        if (m := ORPHAN.match(name)) and not Path(f"/proc/{m.group(2)}").exists():
            orphans.add(m.group(1))
    for prefix in sorted(orphans):
        Lab(0, prefix=prefix).script("down")
    return sorted(orphans)


def wait_until(predicate, what: str, timeout: float, *context) -> None:
    """Poll ``predicate`` until it holds, at most ``timeout`` s; else fail saying ``what`` did
    not happen, with ``context`` (the processes involved, say)."""
    give_up = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > give_up:
            raise AssertionError(f"{what}: not within {timeout} s\n" + "\n".join(map(repr, context)))
        time.sleep(0.01)


@dataclass
class Host:
    """One host of a lab: a network namespace, and its address on the lab's subnet."""

    lab: Lab = field(repr=False)
    index: int
    name: str
    address: str

    def argv(self, argv: list[str]) -> list[str]:
        """``argv`` as a command that runs it on this host (its network, its /dev/shm)."""
        return ["bash", str(SCRIPT), "exec", self.name, *argv]

    def popen(self, argv: list[str], **kw) -> subprocess.Popen:
        """Start ``argv`` on this host; the lab stops it when it goes down."""
        proc = subprocess.Popen(self.argv(argv), env=self.lab.env(kw.pop("env", None)), **kw)
        self.lab.started.append(proc)  # the script hands on its process: this pid is argv's
        return proc

    def run(self, argv: list[str], timeout: float = SCRIPT_TIMEOUT_S, **kw) -> subprocess.CompletedProcess:
        """Run ``argv`` on this host to its end (output captured as text, unless told)."""
        kw.setdefault("capture_output", True)
        kw.setdefault("text", True)
        return subprocess.run(self.argv(argv), check=kw.pop("check", False), env=self.lab.env(kw.pop("env", None)),
                              timeout=timeout, **kw)


class Lab:
    """``size`` hosts on the lab script's subnet, under ``prefix``. Use it as a context manager:
    however the block ends, the processes started on its hosts are stopped and the lab is down."""

    def __init__(self, size: int, prefix: str | None = None, subnet: str = "10.200.77.0/24"):
        self.size, self.prefix, self.subnet = size, prefix or unique_prefix(), subnet
        self.started: list[subprocess.Popen] = []
        net = subnet.rsplit(".", 1)[0]
        self.hosts = [Host(self, i, f"{self.prefix}-h{i}", f"{net}.{i}") for i in range(1, size + 1)]

    def env(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """``base`` (this process's environment if None) plus what names this lab to its script."""
        return dict(os.environ if base is None else base, RETRIEVER_LAB_PREFIX=self.prefix,
                    RETRIEVER_LAB_SUBNET=self.subnet)

    def script(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        done = subprocess.run(["bash", str(SCRIPT), *args], check=False, env=self.env(), capture_output=True,
                              text=True, timeout=SCRIPT_TIMEOUT_S)
        if check and done.returncode:
            raise LabError(f"netns-lab.sh {' '.join(args)} exited {done.returncode}:\n{done.stderr}")
        return done

    def namespaces(self) -> list[str]:
        return [n for n in namespaces() if re.fullmatch(rf"{re.escape(self.prefix)}-(br|h\d+|n\d+)", n)]

    def up(self) -> list[Host]:
        self.script("up", str(self.size))
        return self.hosts

    def partition(self, host: Host) -> None:
        self.script("partition", host.name)

    def heal(self, host: Host) -> None:
        self.script("heal", host.name)

    def nat(self, host: Host) -> str:
        """Put ``host`` behind a NAT gateway (the script's nat): it reaches the lab, nothing
        reaches it. Its address behind the gateway."""
        self.script("nat", host.name)
        return f"192.168.{host.index}.2"

    def unnat(self, host: Host) -> None:
        self.script("unnat", host.name)

    def stop_processes(self) -> None:
        """Stop every process started on the lab's hosts that still runs: SIGTERM, then SIGKILL."""
        for proc in self.started:
            if proc.poll() is None:
                proc.terminate()
        for proc in self.started:
            try:
                proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.started.clear()

    def down(self) -> None:
        self.stop_processes()
        self.script("down")

    def __enter__(self) -> Self:
        self.up()
        return self

    def __exit__(self, *exc) -> None:
        self.down()
