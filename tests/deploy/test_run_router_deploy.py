"""`retriever worker --router ENDPOINT --local-router` in the netns lab: the robot (h3) behind a
masquerading gateway runs its flows through a router of the run's on the robot, linked to the
`retriever router` on h1 (the coordinator's host too); a gpu worker on h2 joins the router on h1
directly. The pipeline (deploy_flows.py ``local``): camera → controller on the robot, camera →
policy on the gpu worker → controller. So camera → controller stays on the robot, and goes on
while the robot is cut off from the router.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from retriever import StepStatus, read_log
from retriever.backends.dora.host import pid_alive
from retriever.backends.zenoh.daemon.run_router import ROUTER_PROCESS_MODULE
from retriever.backends.zenoh.folders import DAEMON_FOLDER
from retriever.replay import replay
from tests.deploy.test_deploy import BOUND_S, FLOWS, HERE, PYTHON, finish, flow_processes, secret  # noqa: F401
from tests.deploy.test_deploy import child_processes, start_worker, wait_going
from tests.deploy.test_router_deploy import start_router
from tests.helpers import poll

#: camera and controller on the robot, the policy on the gpu worker
PLACEMENT = '[nodes]\ncamera = "robot"\ncontroller = "robot"\npolicy = { labels = ["gpu"] }\n'
#: the controller's clock (deploy_flows.py)
PERIOD_NS = 50_000_000
#: how long the robot is cut off from everything: a fifth of Zenoh's default lease (10 s), so no link closes
CUT_S = 2.0


def start_workers(gpu, robot, secret: Path, router: str) -> list[subprocess.Popen]:
    return [start_worker(gpu, "gpu-box", secret, "--path", str(HERE), "--labels", "gpu", router=router),
            start_worker(robot, "robot", secret, "--path", str(HERE), "--local-router", router=router)]


def start_deploy(host, router: str, secret: Path, folder: Path, *extra: str) -> subprocess.Popen:
    placement = folder / "place.toml"
    placement.write_text(PLACEMENT)
    return host.popen([PYTHON, "-m", "retriever.cli", "deploy", f"{FLOWS}:local", "--router", router,
                       "--secret", str(secret), "--placement", str(placement), *extra],
                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=str(HERE.parents[1]))


def run_router_ports(host) -> set[str]:
    """The loopback ports something listens on at ``host`` (its run routers')."""
    listed = host.run(["ss", "-Htln", "src", "127.0.0.1"]).stdout
    return {line.split()[3] for line in listed.splitlines() if line.strip()}


#: on the robot: open a client of the run router at argv[1] with the namespace's password (every
#: daemon's, and every flow's through a plain router), then with none; print what each got
STRANGER = """
import sys, zenoh
from retriever.backends.zenoh.access import RunAccess, read_secret
from retriever.backends.zenoh.hub import client_config
for access in (RunAccess.create("default", read_secret(sys.argv[2])).client_config("default"), None):
    try:
        zenoh.open(client_config(connect=[sys.argv[1]], access=access, shared_memory=False)).close()
        print("admitted")
    except zenoh.ZError:
        print("refused")
"""


def test_a_robot_local_edge_keeps_its_ticks_while_the_robot_is_cut_off(partitionable, hosts, secret, tmp_path):
    """The robot behind NAT, its worker with --local-router: the run goes as placed and replays;
    cut off from the router for CUT_S mid-run, the controller's every tick takes the camera's
    count complete (never incomplete or late on that edge, no tick skipped), while the policy's
    edge goes incomplete and late; the run recovers and ends well. The run router refuses a
    session without the run's password, and is gone after the run."""
    hub, gpu, robot = hosts
    partitionable.nat(robot)
    try:
        router = start_router(hub, secret)
        daemons = start_workers(gpu, robot, secret, router)
        before = run_router_ports(robot)
        log = tmp_path / "run.mcap"
        run = start_deploy(hub, router, secret, tmp_path, "--duration", "9", "--log", str(log))
        wait_going(run, log)
        (port,) = run_router_ports(robot) - before
        tried = robot.run([PYTHON, "-c", STRANGER, f"tcp/{port}", str(secret)], timeout=BOUND_S,
                          cwd=str(HERE.parents[1]))
        assert tried.stdout.split() == ["refused", "refused"], tried.stdout + tried.stderr
        cut_ns = time.time_ns()
        partitionable.partition(robot)
        try:
            time.sleep(CUT_S)  # the cut's length: what the test is about, not a wait for something
        finally:
            partitionable.heal(robot)
            healed_ns = time.time_ns()
        out, err = finish(run)
        assert run.returncode == 0, out + err
        recorded = read_log(log)
        assert json.loads(recorded.run["deployment"])["placed"] == {
            "camera": "robot", "controller": "robot", "policy": "gpu-box"}
        assert not recorded.faults, recorded.faults
        steps = recorded.trace().steps_of("controller")
        during = [s for s in steps if cut_ns <= s.wall_start_ns <= healed_ns]
        assert len(during) >= CUT_S * 1e9 / PERIOD_NS * 0.8, (len(during), len(steps))
        tags = [s.tag[0] for s in during]
        assert all(b - a == PERIOD_NS for a, b in zip(tags, tags[1:])), "a tick of the controller was skipped"
        local_trouble = [s for s in during if s.status not in (StepStatus.OK, StepStatus.INCOMPLETE)
                         or "n" in (s.detail or {}).get("incomplete", ()) or "n" in (s.detail or {}).get("late", {})
                         or "n" not in s.consumed]
        assert not local_trouble, local_trouble[:3]
        cloud_trouble = [s for s in steps if s.wall_start_ns >= cut_ns and (
            "a" in (s.detail or {}).get("incomplete", ()) or "a" in (s.detail or {}).get("late", {}))]
        assert len(cloud_trouble) >= 10, "the policy's edge never went incomplete: was the robot cut off?"
        def command(step) -> int:  # the seq of the policy's command a step took (0: none yet)
            return step.consumed["a"][-1][2] if "a" in step.consumed else 0

        assert command(steps[-1]) > max(map(command, during)), "no command of the policy came after the cut"
        assert replay(recorded).identical
        poll(lambda: not flow_processes(daemons[1].pid), "the robot's flows stopping")
        poll(lambda: run_router_ports(robot) == before, "the run router closing")
    finally:
        partitionable.stop_processes()
        partitionable.unnat(robot)


def run_router_process(daemon_pid: int) -> int:
    """The pid of the live run router process (daemon/router_process.py) a daemon started."""
    found = child_processes(daemon_pid, ROUTER_PROCESS_MODULE)
    assert len(found) <= 1, found
    return found[0] if found else 0


def test_a_run_router_dies_with_its_sigkilled_daemon(hosts, secret, tmp_path):
    """The run router is a process the daemon started for the run: SIGKILLed, the daemon takes
    it along (as it does the run's flows)."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    daemons = start_workers(gpu, robot, secret, router)
    log = tmp_path / "run.mcap"
    run = start_deploy(hub, router, secret, tmp_path, "--duration", "60", "--log", str(log))
    wait_going(run, log)
    pid = poll(lambda: run_router_process(daemons[1].pid), "the robot's run router process")
    flows = flow_processes(daemons[1].pid)
    daemons[1].kill()
    daemons[1].wait()
    try:
        poll(lambda: not pid_alive(pid), "the run router's end after its daemon's")
        poll(lambda: not any(map(pid_alive, flows)), "the robot's flows' end after their daemon's")
    finally:
        run.kill()
        finish(run)
        for left in [pid, *flows]:  # should the assertions fail: a process they waited on outlived its daemon
            if pid_alive(left):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(left, signal.SIGKILL)
        # the killed daemon's run folder (its flows' spec, the run's passwords): its next start would reap it
        for folder in Path(tempfile.gettempdir()).glob(f"{DAEMON_FOLDER}-{daemons[1].pid}-run-*"):
            shutil.rmtree(folder)


def test_a_crashed_run_router_is_reported_to_the_coordinator(hosts, secret, tmp_path):
    """The robot's run router killed mid-run: its daemon tells the coordinator how it ended and
    stops the run's flows there, which have no link to anyone: the run ends with an error, long
    before its duration."""
    hub, gpu, robot = hosts
    router = start_router(hub, secret)
    daemons = start_workers(gpu, robot, secret, router)
    log = tmp_path / "run.mcap"
    run = start_deploy(hub, router, secret, tmp_path, "--duration", "60", "--log", str(log))
    wait_going(run, log)
    pid = poll(lambda: run_router_process(daemons[1].pid), "the robot's run router process")
    robot.run(["kill", "-KILL", str(pid)], timeout=BOUND_S)
    killed = time.monotonic()
    out, err = finish(run)
    assert time.monotonic() - killed < BOUND_S / 2, "the run went on without the robot's flows"
    assert re.search(r"error: run \S+: the worker's router for it \(pid %d, tcp/127\.0\.0\.1:\d+\) was killed by "
                     r"SIGKILL; the run's flows on this machine have no link to anyone" % pid, out + err), out + err
    assert run.returncode != 0
