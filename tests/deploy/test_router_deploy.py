"""`retriever deploy --router` in the netns lab: a `retriever router` on h1 (the coordinator's
host too), a worker labelled gpu on h2 and a "robot" worker on h3, every session a client of the
router (none listens). The pipeline of deploy_flows.py stands for a robot's: its counter (the
camera) and sink (the controller) on the robot, its relay (the policy) on the gpu worker.
"""

from __future__ import annotations

import json
import re
import secrets
import select
import signal
import subprocess
import time
from pathlib import Path

from retriever import read_log
from retriever.replay import replay
from tests.deploy.test_deploy import (BOUND_S, FLOWS, HERE, PYTHON, finish, flow_processes, secret,  # noqa: F401
                                     start_worker, wait_going)
from tests.helpers import poll

PORT = 7448


def start_router(host, secret: Path) -> str:
    """A `retriever router` on ``host``; its endpoint, once it listens."""
    at = f"tcp/{host.address}:{PORT}"
    proc = host.popen([PYTHON, "-m", "retriever.cli", "router", "--listen", at, "--secret", str(secret)],
                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    give_up, seen = time.monotonic() + BOUND_S, []
    while time.monotonic() < give_up:
        if select.select([proc.stderr], [], [], 0.1)[0]:
            seen.append(proc.stderr.readline())
            if seen[-1].startswith("retriever router listening on"):
                return at
        assert proc.poll() is None, f"the router exited {proc.returncode}: {''.join(seen)}{proc.stderr.read()}"
    raise AssertionError(f"the router did not start within {BOUND_S:g} s: {''.join(seen)}")


def deploy_through(host, router: str, secret: Path, *extra: str) -> subprocess.CompletedProcess:
    return host.run([PYTHON, "-m", "retriever.cli", "deploy", f"{FLOWS}:pipe", "--router", router,
                     "--secret", str(secret), *extra], timeout=BOUND_S, cwd=str(HERE.parents[1]))


#: the robot's pipeline placed as a robot's: camera and controller on the robot, the policy on a gpu worker
PLACEMENT = '[nodes]\ncounter = "robot"\nrelay = { labels = ["gpu"] }\nsink = "robot"\n'


def start_workers(gpu, robot, secret: Path, router: str) -> list[subprocess.Popen]:
    """The gpu-labelled worker and the robot's worker, both joined through ``router``."""
    return [start_worker(gpu, "gpu-box", secret, "--path", str(HERE), "--labels", "gpu", router=router),
            start_worker(robot, "robot", secret, "--path", str(HERE), router=router)]


def placement_file(folder: Path) -> Path:
    path = folder / "place.toml"
    path.write_text(PLACEMENT)
    return path


def start_deploy_through(host, router: str, secret: Path, *extra: str) -> subprocess.Popen:
    """`retriever deploy --router` going on ``host``, its output piped."""
    return host.popen([PYTHON, "-m", "retriever.cli", "deploy", f"{FLOWS}:pipe", "--router", router, "--secret",
                       str(secret), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                      cwd=str(HERE.parents[1]))


def other_secret(folder: Path) -> Path:
    path = folder / "other.key"
    path.write_text(secrets.token_hex(32) + "\n")
    path.chmod(0o600)
    return path


def test_a_deployment_through_a_router_runs_as_placed_and_its_log_replays(hosts, secret, tmp_path):
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    start_workers(gpu, robot, secret, router)
    placement = placement_file(tmp_path)
    log = tmp_path / "run.mcap"
    done = deploy_through(hub, router, secret, "--placement", str(placement), "--duration", "3", "--log", str(log))
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"deployment joined through router {router}" in done.stderr, done.stderr
    recorded = read_log(log)
    placed = json.loads(recorded.run["deployment"])["placed"]
    assert placed == {"counter": "robot", "relay": "gpu-box", "sink": "robot"}, placed
    trace = recorded.trace()
    assert len(trace.steps_of("counter")) >= 50 and len(trace.steps_of("sink")) >= 40
    assert replay(recorded).identical


def test_a_session_without_the_secret_is_refused_at_the_router(hosts, secret, tmp_path):
    hub, gpu, _ = hosts
    router = start_router(hub, secret)
    other = other_secret(tmp_path)
    done = deploy_through(hub, router, other, "--duration", "2")
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"the deployment found no router that admits it at {router}: it wants another --secret" in done.stderr, \
        done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    worker = gpu.run([PYTHON, "-m", "retriever.cli", "worker", "--name", "stranger", "--router", router,
                      "--secret", str(other)], timeout=BOUND_S, cwd=str(HERE.parents[1]))
    assert worker.returncode == 1, worker.stdout + worker.stderr
    assert f"retriever-worker 'stranger' found no router that admits it at {router}" in worker.stderr, worker.stderr


def test_a_deployment_with_no_router_there_says_so(hosts, secret):
    hub, _, _ = hosts
    done = deploy_through(hub, f"tcp/{hub.address}:{PORT}", secret, "--duration", "2")
    assert done.returncode == 1, done.stdout + done.stderr
    assert "nothing listens there" in done.stderr and "retriever router --listen" in done.stderr, done.stderr


def test_a_deployment_that_loses_its_router_stops_saying_so(hosts, secret, tmp_path):
    """The router killed mid-run: the coordinator stops the run naming the router (no traceback),
    the log up to then is kept, and the workers stop the run's flows (they lost its token)."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    router_proc = hub.lab.started[-1]
    workers = start_workers(gpu, robot, secret, router)
    log = tmp_path / "run.mcap"
    run = start_deploy_through(hub, router, secret, "--duration", "60", "--log", str(log))
    wait_going(run, log)
    router_proc.send_signal(signal.SIGKILL)
    out, err = finish(run)
    assert run.returncode == 1, out + err
    assert f"the deployment lost its router {router}" in err and "Traceback" not in err, err
    assert f"the run up to the error is in {log}" in err, err
    poll(lambda: not any(flow_processes(w.pid) for w in workers), "the workers' flows stopped")


def test_a_robot_behind_nat_takes_part_through_the_router(partitionable, hosts, secret, tmp_path):
    """The robot's host behind a masquerading gateway (netns-lab.sh nat, nftables: the fixture
    skips without): nothing reaches it, it reaches the router; its camera and controller run
    there, the policy on the gpu worker."""
    hub, gpu, robot = hosts
    inside = partitionable.nat(robot)
    try:
        unreached = hub.run([PYTHON, "-c", f"import socket; socket.create_connection(('{inside}', 7447), timeout=2)"])
        assert unreached.returncode != 0, "the robot behind NAT was reached from outside"
        router = start_router(hub, secret)
        start_workers(gpu, robot, secret, router)
        placement = placement_file(tmp_path)
        log = tmp_path / "run.mcap"
        done = deploy_through(hub, router, secret, "--placement", str(placement), "--duration", "3",
                              "--log", str(log))
        assert done.returncode == 0, done.stdout + done.stderr
        recorded = read_log(log)
        assert json.loads(recorded.run["deployment"])["placed"]["counter"] == "robot"
        assert len(recorded.trace().steps_of("sink")) >= 40
        assert replay(recorded).identical
    finally:
        partitionable.stop_processes()
        partitionable.unnat(robot)


def test_a_robot_cut_off_from_the_router_for_two_seconds_loses_nothing(partitionable, hosts, secret, tmp_path):
    """The robot's host partitioned from everything for 2 s (shorter than Zenoh's default 10 s
    lease) mid-run: its camera goes on ticking, what it produced reaches the policy late, once
    the link heals (TCP retransmits), and nothing is lost: every frame is relayed, no fault, and
    the log replays."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    start_workers(gpu, robot, secret, router)
    placement = placement_file(tmp_path)
    log = tmp_path / "run.mcap"
    run = start_deploy_through(hub, router, secret, "--placement", str(placement), "--duration", "8", "--log", str(log))
    wait_going(run, log)
    partitionable.partition(robot)
    try:
        time.sleep(2.0)  # the partition's length: what the test is about, not a wait for something
    finally:
        partitionable.heal(robot)
    out, err = finish(run)
    assert run.returncode == 0, out + err
    recorded = read_log(log)
    assert not recorded.faults, recorded.faults
    trace = recorded.trace()
    relayed = {event for step in trace.steps_of("relay") for ids in step.consumed.values() for event in ids}
    counted = trace.steps_of("counter")
    end_ns = counted[-1].tag[0]
    # every frame made a second or more before the end was relayed (the last ones may come too late for the run)
    unrelayed = [event for step in counted if step.tag[0] < end_ns - 1e9 for event in step.produced
                 if event not in relayed]
    assert len(counted) > 100 and not unrelayed, (len(counted), unrelayed[:10])
    starts = sorted(step.wall_start_ns for step in trace.steps_of("relay"))
    assert max(b - a for a, b in zip(starts, starts[1:])) > 1.5e9, "the policy never waited: was the robot cut off?"
    assert replay(recorded).identical


#: a watcher on the coordinator's host: joins with the file the run wrote and counts the samples it sees
WATCHER = """
import sys, threading, zenoh
seen, enough = [], threading.Event()
with zenoh.open(zenoh.Config.from_file(sys.argv[1])) as session:
    def take(sample):
        seen.append(1)
        if len(seen) >= 20:
            enough.set()
    subscriber = session.declare_subscriber(sys.argv[2], take)
    enough.wait(float(sys.argv[3]))
    subscriber.undeclare()
print(len(seen))
"""


def test_a_watcher_joins_a_routed_deployment_with_the_file_it_wrote(hosts, secret, tmp_path):
    """Through a router the watcher's user is the namespace's (access.watch_user): the file the
    coordinator names lets a plain Zenoh client see the run's events there, read-only."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    start_workers(gpu, robot, secret, router)
    run = start_deploy_through(hub, router, secret, "--duration", "8")
    said, give_up = [], time.monotonic() + BOUND_S
    while not any("watch it read-only" in line for line in said) and time.monotonic() < give_up:
        if select.select([run.stderr], [], [], 0.1)[0]:
            said.append(run.stderr.readline())
        assert run.poll() is None or said[-1:] != [""], f"the deployment ended: {''.join(said)}"
    (line,) = [line for line in said if "watch it read-only" in line]
    found = re.search(r"from_file\('([^']+)'\) and a subscriber on (\S+)", line)
    assert found, line
    watched = hub.run([PYTHON, "-c", WATCHER, found[1], found[2], "30"], timeout=BOUND_S)
    out, err = finish(run)
    assert run.returncode == 0, "".join(said) + err
    assert watched.returncode == 0 and int(watched.stdout.split()[-1]) >= 20, watched.stdout + watched.stderr


def test_workers_status_and_stop_through_the_router(hosts, secret, tmp_path):
    """`retriever workers | status | stop --router`: asked from the gpu host through the router, as
    through a worker without one; the deployment stops as Ctrl-C at its coordinator would."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    daemons = start_workers(gpu, robot, secret, router)
    ask = [PYTHON, "-m", "retriever.cli"]
    where = ["--router", router, "--secret", str(secret)]
    listed = poll(lambda: (done := gpu.run([*ask, "workers", *where], timeout=BOUND_S)).returncode == 0
                  and "robot" in done.stdout and "gpu-box" in done.stdout and done, "both workers listed")
    assert "gpu" in listed.stdout, listed.stdout
    log = tmp_path / "run.mcap"
    run = start_deploy_through(hub, router, secret, "--duration", "60", "--log", str(log))
    wait_going(run, log)

    def status() -> str:
        shown = gpu.run([*ask, "status", *where], timeout=BOUND_S)
        assert shown.returncode == 0, shown.stderr
        return shown.stdout if " t = " in shown.stdout else ""

    shown = poll(status, "a status of the running deployment")
    assert "lab in namespace 'default'" in shown and "counter" in shown, shown
    stopped = gpu.run([*ask, "stop", *where], timeout=BOUND_S)
    assert stopped.returncode == 0 and "stopping deployment lab" in stopped.stdout, stopped.stderr
    out, err = finish(run)
    assert run.returncode == 130, err  # as Ctrl-C at the coordinator
    poll(lambda: not any(flow_processes(d.pid) for d in daemons), "the flows stopping", bound=10.0)
    both = gpu.run([*ask, "status", "--connect", router, *where], timeout=BOUND_S)
    assert both.returncode == 1 and "--connect and --router both given" in both.stderr, both.stderr
