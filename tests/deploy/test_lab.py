"""The netns lab (deploy/netns-lab.sh) and a run's Zenoh sessions across it, over real TCP (issue 18).

The lab makes its namespaces and removes exactly those. Two peers of a run on two hosts exchange
puts, authenticated with the run's password (access.py); on a third host, a peer of the same run
is heard, and strangers (no password, another run's password) get no link: they hear nothing and
nobody hears them. A partitioned host's puts stop arriving; healed, it links up again and its new
puts arrive, the ones made while it was cut off never.
"""

from __future__ import annotations

import inspect
import json
import re
from pathlib import Path

import pytest

from retriever.backends.zenoh.access import RunAccess, write_private
from tests.deploy import test_deploy, test_retriever0_deploy
from tests.deploy.lab import SCRIPT, Lab, namespaces, partitions_unavailable, unavailable, wait_until
from tests.deploy.zenoh_peer import Peer

BOUND_S = 15.0  # a bound on any wait, never a speed check
#: a link whose other end went silent is closed after this (Zenoh's default is 10 s): the partition
#: test waits for it twice
LEASE_MS = 1000
#: puts of the partitioned host that the test sees it make after its link dropped
PUTS_WHILE_CUT_OFF = 5
#: the strangers' window: they retry their link every 0.2 s at most (hub.peer_config) while this
#: many puts of the run's own peers arrive (0.05 s apart)
STRANGER_WINDOW_PUTS = 20


def run_access(directory: Path) -> Path:
    """A new run's credentials as a spec file (what a worker reads), with its dictionary beside it."""
    directory.mkdir()
    access = RunAccess.create("lab")
    spec = access.to_spec(access.write_dictionary(directory))
    return write_private(directory / "run.json", json.dumps(spec))


def test_up_makes_a_lab_and_down_removes_exactly_it(lab):
    theirs = set(lab.namespaces())  # the session's lab, up beside this one
    assert len(theirs) == 1 + len(lab.hosts)
    mine = Lab(2, subnet="10.200.78.0/24")
    try:
        h1, h2 = mine.up()
        assert set(mine.namespaces()) == {f"{mine.prefix}-br", h1.name, h2.name}
        assert "inet 10.200.78.2/24" in h2.run(["ip", "-4", "-o", "addr", "show", "eth0"], check=True).stdout
        assert re.search(r"<[^>]*\bUP\b", h2.run(["ip", "-o", "link", "show", "lo"], check=True).stdout)
        # each host has its own /dev/shm: Zenoh peers on two hosts cannot meet in shared memory
        h1.run(["touch", "/dev/shm/h1-was-here"], check=True)
        assert h2.run(["ls", "/dev/shm"], check=True).stdout == ""
        assert not Path("/dev/shm/h1-was-here").exists()
        again = mine.script("up", "2", check=False)
        assert again.returncode == 1 and f"a lab '{mine.prefix}' exists" in again.stderr
    finally:
        mine.down()
    assert not [n for n in namespaces() if n.startswith(mine.prefix)]
    assert not list(Path("/dev/shm").glob(f"{mine.prefix}-*"))
    assert set(lab.namespaces()) == theirs
    assert mine.script("down").returncode == 0  # nothing there: fine


def test_the_script_says_how_to_call_it():
    if reason := unavailable():
        pytest.skip(reason)
    lab = Lab(1)
    assert lab.script(check=False).stderr.startswith(
        f"usage: {SCRIPT.name} up N | down | exec HOST PROGRAM [ARG …] | partition HOST | heal HOST")
    assert "N is the number of hosts, 1 to 253; got '0'" in lab.script("up", "0", check=False).stderr
    assert f"no host '1' in lab '{lab.prefix}'" in lab.script("heal", "1", check=False).stderr


def test_without_nft_on_the_path_partitions_are_unavailable_and_the_reason_says_how_to_get_them(tmp_path):
    assert partitions_unavailable(path=str(tmp_path)) == (
        "partitions need nftables ('nft' not on PATH): apt-get install nftables (.ci/run installs it)")
    nft = tmp_path / "nft"
    nft.write_text("#!/bin/sh\n")
    nft.chmod(0o755)
    assert partitions_unavailable(path=str(tmp_path)) is None


def test_every_test_that_partitions_a_host_takes_the_fixture_that_skips_without_nftables():
    """Only the partitionable fixture skips where nft is missing; a test that partitions through
    the plain lab fails there (the script: 'nft' not found) instead of skipping as the README says."""
    import sys
    # (a test may partition through a helper of its module, which then takes the fixture from it)
    partitioning = {name: fn for module in (sys.modules[__name__], test_deploy, test_retriever0_deploy)
                    for name, fn in vars(module).items()
                    if inspect.isfunction(fn) and fn.__module__ == module.__name__
                    and re.search(r"\w\.partition\(\w", inspect.getsource(fn))}
    assert len(partitioning) == 3, sorted(partitioning)
    assert [n for n, fn in partitioning.items() if "partitionable" not in inspect.signature(fn).parameters] == []


def test_a_run_crosses_hosts_and_strangers_get_nothing(hosts, tmp_path):
    h1, h2, h3 = hosts
    run, other_run = run_access(tmp_path / "run"), run_access(tmp_path / "other")
    listen = f"tcp/{h1.address}:7447"
    p1 = Peer(h1, "h1", listen=[listen], access=run)
    strangers = [Peer(h3, "nopass", connect=[listen]), Peer(h3, "otherpass", connect=[listen], access=other_run)]
    p2 = Peer(h2, "h2", connect=[listen], access=run)
    p3 = Peer(h3, "h3", connect=[listen], access=run)  # from the strangers' host, with the password
    peers = [p1, p2, p3, *strangers]

    wait_until(lambda: p1.got("lab/h2") and p1.got("lab/h3") and p2.got("lab/h1") and p3.got("lab/h1"),
               "the run's peers exchange puts", BOUND_S, *peers)
    wait_until(lambda: all(s.ready() for s in strangers), "the strangers open their sessions", BOUND_S, *strangers)
    heard = len(p1.got("lab/h2"))
    wait_until(lambda: len(p1.got("lab/h2")) >= heard + STRANGER_WINDOW_PUTS, "h2 goes on", BOUND_S, p1, p2)

    for stranger in strangers:
        assert stranger.keys() == set() and stranger.peers() == 0, stranger
    for peer in (p1, p2, p3):
        assert not peer.keys() & {"lab/nopass", "lab/otherpass"}, peer
    assert [peer.stop() for peer in peers] == [0] * len(peers)


def test_a_partitioned_host_is_cut_off_until_healed(partitionable, hosts, tmp_path):
    lab = partitionable
    h1, h2, _ = hosts
    run = run_access(tmp_path / "run")
    listen = f"tcp/{h1.address}:7448"
    p1 = Peer(h1, "h1", listen=[listen], access=run, lease_ms=LEASE_MS)
    p2 = Peer(h2, "h2", connect=[listen], access=run, lease_ms=LEASE_MS)
    wait_until(lambda: p1.got("lab/h2") and p2.got("lab/h1"), "h1 and h2 exchange puts", BOUND_S, p1, p2)

    partitioned_at = len(p2.events)
    lab.partition(h2)
    wait_until(lambda: p1.peers() == 0 and p2.peers() == 0, "both ends drop the link (lease)", BOUND_S, p1, p2)
    # h2 saw its link drop, so the partition was in place when it made each of its puts after that
    dropped = next(i for i, e in enumerate(p2.events) if i >= partitioned_at and e.get("peers") == 0)
    wait_until(lambda: len(p2.sent(dropped)) >= PUTS_WHILE_CUT_OFF, "h2 goes on putting", BOUND_S, p2)
    cut_off = set(p2.sent(dropped))
    assert not cut_off & set(p1.got("lab/h2")), p1

    healed_at = len(p1.events), len(p2.events)
    lab.heal(h2)
    wait_until(lambda: p1.got("lab/h2", since=healed_at[0]) and p2.got("lab/h1", since=healed_at[1]),
               "h1 and h2 hear each other again", BOUND_S, p1, p2)
    assert min(p1.got("lab/h2", since=healed_at[0])) > max(cut_off)
    assert not cut_off & set(p1.got("lab/h2")), "a put made while cut off arrived late"
    assert [p1.stop(), p2.stop()] == [0, 0]
