"""What a Python Zenoh session in router mode does for a run (issue 38 §2): a probe, not a test.

    python benchmarks/router_probe.py functions     routing, auth, ACL, peers vs clients (one process)
    python benchmarks/router_probe.py tls DIR       mutual TLS at the router (certificates made in DIR)
    python benchmarks/router_probe.py latency [T…]  put→subscriber latency: direct peers, clients of a router,
                                                    clients of two linked routers (TOPOLOGIES)
    python benchmarks/router_probe.py links N MODE  N client or peer sessions through one router: links, startup
    python benchmarks/router_probe.py robot         (root) a robot-local edge in the netns lab, the robot behind
                                                    NAT: through a router on the robot linked to the remote
                                                    one, through the remote router, and direct (ROBOT_TOPOLOGIES);
                                                    and through Retriever's own run router (--local-router)

Every session listens and connects on loopback (``robot``: the netns lab's addresses) with multicast
scouting off. Prints one line per check. Plain zenoh-python sessions, but for ``robot``'s "run
router", which is Retriever's (daemon/run_router.py), linked to a ``retriever router``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

BASE_PORT = 27447


def config(mode: str, listen=(), connect=(), user=None, password=None, dictionary=None, extra=None) -> zenoh.Config:
    """A session config from plain values (multicast off, quick reconnects)."""
    doc = {"mode": mode, "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
           "scouting": {"multicast": {"enabled": False}}}
    if mode != "client":
        doc["connect"]["retry"] = {"period_init_ms": 100, "period_max_ms": 200, "period_increase_factor": 1.5}
    usrpwd = {k: v for k, v in (("user", user), ("password", password), ("dictionary_file", dictionary)) if v}
    if usrpwd:
        doc["transport"] = {"auth": {"usrpwd": usrpwd}}
    c = zenoh.Config.from_json5(json.dumps(doc))
    for key, value in (extra or {}).items():
        c.insert_json5(key, value)
    return c


def ep(i: int, proto: str = "tcp") -> str:
    return f"{proto}/127.0.0.1:{BASE_PORT + i}"


def watcher_acl() -> str:
    """access.py's rules, in short: the watcher may not put; everyone else may do anything."""
    return json.dumps({
        "enabled": True, "default_permission": "allow",
        "rules": [{"id": "ro", "messages": ["put", "delete", "query", "reply", "declare_queryable",
                                            "liveliness_token"], "flows": ["ingress"], "permission": "deny",
                   "key_exprs": ["**"]}],
        "subjects": [{"id": "w", "usernames": ["watch"]}],
        "policies": [{"rules": ["ro"], "subjects": ["w"]}]})


#: peers joined to one router only: (what, config entries, whether the peers listen)
PEER_VARIANTS = [
    ("gossip on (default)", {}, True),
    ("gossip off", {"scouting/gossip/enabled": "false"}, True),
    ("gossip on, peers never autoconnect to peers", {"scouting/gossip/autoconnect": '{router: [], peer: ["router"]}'},
     True),
    ("gossip on (default), peers do not listen", {}, False),
]


def say(name: str, ok: bool, detail: str = "") -> None:
    print(f"{'PASS' if ok else 'FAIL'}  {name}{'  (' + detail + ')' if detail else ''}", flush=True)


def exchange(a: zenoh.Session, b: zenoh.Session, tag: str) -> dict[str, bool]:
    """put/subscribe, queryable/get and liveliness from a to b (b declares, a uses)."""
    got, live = [], []
    sub = b.declare_subscriber(f"{tag}/data/**", lambda s: got.append(s.payload.to_bytes()))
    qbl = b.declare_queryable(f"{tag}/q", lambda q: q.reply(f"{tag}/q", b"answer"))
    tok = b.liveliness().declare_token(f"{tag}/live/b")
    lsub = a.liveliness().declare_subscriber(f"{tag}/live/*", lambda s: live.append(str(s.kind)), history=True)
    time.sleep(0.5)
    for i in range(5):
        a.put(f"{tag}/data/x", f"m{i}".encode())
    replies = [r.ok.payload.to_bytes() for r in a.get(f"{tag}/q", timeout=2) if r.ok is not None]
    tokens = [str(r.ok.key_expr) for r in a.liveliness().get(f"{tag}/live/*", timeout=2) if r.ok is not None]
    time.sleep(0.3)
    result = {"put/sub": len(got) == 5, "get": replies == [b"answer"], "liveliness get": tokens == [f"{tag}/live/b"],
              "liveliness sub": "SampleKind.PUT" in live}
    for d in (sub, qbl, tok, lsub):
        d.undeclare()
    return result


def functions() -> None:
    folder = tempfile.mkdtemp(prefix="router-probe-")
    dictionary = os.path.join(folder, "users.txt")
    with open(dictionary, "w") as f:
        f.write("run:runpw\nwatch:watchpw\n")
    router_cfg = config("router", listen=[ep(0)], user="run", password="runpw", dictionary=dictionary,
                        extra={"access_control": watcher_acl(), "routing/router/peers_failover_brokering": "true"})
    with zenoh.open(router_cfg) as router:
        # 1. clients with the run's password: everything routes through the router
        with zenoh.open(config("client", connect=[ep(0)], user="run", password="runpw")) as c1, \
                zenoh.open(config("client", connect=[ep(0)], user="run", password="runpw")) as c2:
            for what, ok in exchange(c1, c2, "cc").items():
                say(f"client->router->client {what}", ok)
            say("client sees the router only", [str(z) for z in c1.info.routers_zid()] == [str(router.zid())]
                and not list(c1.info.peers_zid()))
            kinds = sorted(str(t.whatami) for t in router.info.transports())
            say("router has one transport per client", kinds == ["client", "client"], f"{kinds}")
        # 2. no password / wrong password
        for label, kw in (("no credentials", {}), ("wrong password", {"user": "run", "password": "nope"})):
            try:
                with zenoh.open(config("client", connect=[ep(0)], **kw)):
                    say(f"client with {label} refused", False, "zenoh.open succeeded")
            except zenoh.ZError as e:
                say(f"client with {label} refused", True, f"zenoh.open raised ZError: {str(e)[:90]}")
        t0 = time.monotonic()
        with zenoh.open(config("peer", connect=[ep(0)], listen=[ep(9)])) as p:
            time.sleep(1.0)
            say("peer without credentials gets no link", not list(p.info.routers_zid()),
                f"open took {time.monotonic() - t0 - 1.0:.2f}s, routers={len(list(p.info.routers_zid()))}")
        # 3. the watcher: reads through the router, its puts dropped by the router's ACL
        with zenoh.open(config("client", connect=[ep(0)], user="run", password="runpw")) as c1, \
                zenoh.open(config("client", connect=[ep(0)], user="watch", password="watchpw")) as w:
            seen, from_watcher = [], []
            wsub = w.declare_subscriber("acl/x", lambda s: seen.append(1))
            csub = c1.declare_subscriber("acl/w/**", lambda s: from_watcher.append(1))
            time.sleep(0.5)
            for _ in range(3):
                c1.put("acl/x", b"1")
                w.put("acl/w/x", b"2")
            time.sleep(0.5)
            say("watcher receives through the router", len(seen) == 3, f"{len(seen)}/3")
            say("router's ACL drops the watcher's put", not from_watcher, f"{len(from_watcher)} arrived")
            wsub.undeclare()
            csub.undeclare()
        # 4. peers with the run's password, connected to the router only
        for label, extra, listen in PEER_VARIANTS:
            with zenoh.open(config("peer", connect=[ep(0)], listen=[ep(1)] if listen else [], user="run",
                                   password="runpw", dictionary=dictionary, extra=extra)) as p1, \
                    zenoh.open(config("peer", connect=[ep(0)], listen=[ep(2)] if listen else [], user="run",
                                      password="runpw", dictionary=dictionary, extra=extra)) as p2:
                time.sleep(3)
                mesh = len(list(p1.info.peers_zid()))
                results = exchange(p1, p2, f"pp{abs(hash(label)) % 1000}")
                say(f"peer->peer with a router, {label}", all(results.values()),
                    f"{sum(results.values())}/4 of put/sub, get, liveliness get/sub; direct links: {mesh}")
    # 5. a router that connects out to a listening peer that checks passwords: does it prove its own?
    with zenoh.open(config("peer", listen=[ep(3)], user="run", password="runpw", dictionary=dictionary)) as lp:
        for label, kw, expected in (("with the run's password gets", {"user": "run", "password": "runpw"}, True),
                                    ("without a password gets no", {}, False)):
            with zenoh.open(config("router", listen=[ep(4)], connect=[ep(3)], **kw)):
                time.sleep(1.0)
                say(f"router connecting out {label} link", bool(list(lp.info.routers_zid())) == expected,
                    f"listener routers_zid={len(list(lp.info.routers_zid()))}")
            time.sleep(0.3)
    # 6. two routers, clients on each: routed router to router
    with zenoh.open(config("router", listen=[ep(5)], user="run", password="runpw", dictionary=dictionary)), \
            zenoh.open(config("router", listen=[ep(6)], connect=[ep(5)], user="run", password="runpw",
                              dictionary=dictionary)), \
            zenoh.open(config("client", connect=[ep(5)], user="run", password="runpw")) as ca, \
            zenoh.open(config("client", connect=[ep(6)], user="run", password="runpw")) as cb:
        time.sleep(1.0)
        for what, ok in exchange(ca, cb, "rr").items():
            say(f"client->router->router->client {what}", ok)
    os.remove(dictionary)
    os.rmdir(folder)


def make_certs(folder: str) -> dict[str, str]:
    """A CA, a router certificate for 127.0.0.1, a client certificate, and a rogue self-signed one."""
    def run(*args):
        subprocess.run(args, cwd=folder, check=True, capture_output=True)
    run("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
        "-days", "1", "-subj", "/CN=probe-ca")
    with open(os.path.join(folder, "san.ext"), "w") as f:
        f.write("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    for name in ("router", "client"):
        run("openssl", "req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
            "-subj", f"/CN={name}")
        run("openssl", "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", "1", "-extfile", "san.ext")
    run("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "rogue.key", "-out", "rogue.pem",
        "-days", "1", "-subj", "/CN=rogue")
    return {n: os.path.join(folder, n) for n in os.listdir(folder)}


def tls_entry(f: dict[str, str], ca: str, name: str) -> str:
    return json.dumps({"root_ca_certificate": f[ca], "enable_mtls": True,
                       "listen_certificate": f[f"{name}.pem"], "listen_private_key": f[f"{name}.key"],
                       "connect_certificate": f[f"{name}.pem"], "connect_private_key": f[f"{name}.key"]})


def tls(folder: str) -> None:
    f = make_certs(folder)
    dictionary = os.path.join(folder, "users.txt")
    with open(dictionary, "w") as out:
        out.write("run:runpw\n")
    with zenoh.open(config("router", listen=[ep(7, "tls")], user="run", password="runpw", dictionary=dictionary,
                           extra={"transport/link/tls": tls_entry(f, "ca.pem", "router")})):
        with zenoh.open(config("client", connect=[ep(7, "tls")], user="run", password="runpw",
                               extra={"transport/link/tls": tls_entry(f, "ca.pem", "client")})) as c1, \
                zenoh.open(config("client", connect=[ep(7, "tls")], user="run", password="runpw",
                                  extra={"transport/link/tls": tls_entry(f, "ca.pem", "client")})) as c2:
            for what, ok in exchange(c1, c2, "tls").items():
                say(f"mTLS client->router->client {what}", ok)
        try:
            with zenoh.open(config("client", connect=[ep(7, "tls")], user="run", password="runpw",
                                   extra={"transport/link/tls": tls_entry(f, "rogue.pem", "rogue")})):
                say("rogue certificate refused", False, "open succeeded")
        except zenoh.ZError as e:
            say("rogue certificate refused", True, f"ZError: {str(e)[:80]}")
        try:
            with zenoh.open(config("client", connect=[ep(7, "tls")],
                                   extra={"transport/link/tls": tls_entry(f, "ca.pem", "client")})):
                say("right certificate, no password refused", False, "open succeeded")
        except zenoh.ZError as e:
            say("right certificate, no password refused", True, f"ZError: {str(e)[:80]}")


#: (payload bytes, samples, puts a second)
LATENCY_SIZES = [(64, 300, 100), (1 << 20, 300, 50), (16 << 20, 40, 5)]
WARMUP = 10


def shm_entry(shm: bool) -> dict[str, str]:
    return {"transport/shared_memory/enabled": "true" if shm else "false"}


def role(argv: list[str]) -> None:
    """One process of the latency measurement: ``router EP SHM [CONNECT]``, ``sub MODE LISTEN CONNECT SHM N`` or
    ``pub MODE LISTEN CONNECT SHM SIZE N RATE`` (LISTEN/CONNECT: an endpoint or -)."""
    kind, rest = argv[0], argv[1:]
    if kind == "router":
        with zenoh.open(config("router", listen=[rest[0]], connect=rest[2:3], extra=shm_entry(rest[1] == "1"))):
            sys.stdin.read()  # until the parent closes it
        return
    if kind == "runrouter":
        run_router(*rest)
        return
    mode, listen, connect, shm = rest[0], rest[1], rest[2], rest[3] == "1"
    # PROBE_ACCESS: config entries with the run's password, for a client of a run router (robot);
    # PROBE_KEY: the key they talk on (a run router admits its namespace's keys alone)
    c = config(mode, listen=[listen] if listen != "-" else [], connect=[connect] if connect != "-" else [],
               extra={**shm_entry(shm), **json.loads(os.environ.get("PROBE_ACCESS", "{}"))})
    with zenoh.open(c) as s:
        if kind == "sub":
            n, got, done = int(rest[4]), [], threading.Event()

            def take(sample):
                now = time.monotonic_ns()
                raw = sample.payload.to_bytes()
                seq, sent = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
                if seq >= WARMUP:
                    got.append((now - sent) / 1e3)
                if len(got) >= n:
                    done.set()
            sub = s.declare_subscriber(os.environ.get("PROBE_KEY", "lat/x"), take)
            print("ready", flush=True)
            done.wait(120)
            sub.undeclare()
            got.sort()
            print(json.dumps({"n": len(got), "p50_us": got[len(got) // 2] if got else None,
                              "p90_us": got[int(len(got) * 0.9)] if got else None}), flush=True)
        else:
            size, n, rate = int(rest[4]), int(rest[5]), float(rest[6])
            pub = s.declare_publisher(os.environ.get("PROBE_KEY", "lat/x"), express=True, congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(1.5)  # the subscriber's declaration arrives
            pad = bytes(max(0, size - 16))
            for seq in range(n + WARMUP):
                pub.put(seq.to_bytes(8, "little") + time.monotonic_ns().to_bytes(8, "little") + pad)
                time.sleep(1 / rate)
            time.sleep(1.0)
            pub.undeclare()


def spawn(*args: str, stdin=None, host=None, env=None) -> subprocess.Popen:
    """A process of ``role``, here or on ``host`` of the netns lab (tests/deploy/lab.py), with
    ``env`` added to its environment."""
    argv = [sys.executable, os.path.abspath(__file__), "role", *args]
    env = {**os.environ, **(env or {})}
    return (host.popen if host is not None else subprocess.Popen)(argv, stdout=subprocess.PIPE, stdin=stdin, text=True,
                                                                   env=env)


def measure(sub_args: tuple, pub_args: tuple, shm: bool, size: int, n: int, rate: float, host=None, env=None) -> str:
    """One put→subscriber latency measurement (``role`` sub and pub, here or on ``host``): what the subscriber said."""
    sub = spawn("sub", *sub_args, "1" if shm else "0", str(n), host=host, env=env)
    sub.stdout.readline()
    pub = spawn("pub", *pub_args, "1" if shm else "0", str(size), str(n), str(rate), host=host, env=env)
    out = sub.stdout.readline()
    pub.wait(timeout=180)
    sub.wait(timeout=30)
    return out.strip()


TOPOLOGIES = ("direct peers", "router, clients", "2 routers, clients")


def latency(topologies: list[str]) -> None:
    """Each of ``topologies`` (TOPOLOGIES; all if none given), shared memory off then on; then
    each topology's median against the direct peers' of the same size and shm (same run)."""
    medians: dict[tuple[int, bool, str], float] = {}
    for size, n, rate in LATENCY_SIZES:
        for shm in (False, True):
            for topology in topologies or TOPOLOGIES:
                medians[(size, shm, topology)] = latency_once(topology, shm, size, n, rate)
    print("\nmedian / direct peers' median (same run):", flush=True)
    for (size, shm, topology), p50 in medians.items():
        direct = medians.get((size, shm, "direct peers"))
        if topology != "direct peers" and direct and p50:
            print(f"{size:>9} B  {topology:<18} shm={'on ' if shm else 'off'}  {p50 / direct:5.2f}x  "
                  f"({p50 - direct:+,.0f} us)", flush=True)


def latency_once(topology: str, shm: bool, size: int, n: int, rate: float) -> float | None:
        procs = []
        if topology == "direct peers":
            sub_args, pub_args = ("peer", ep(41), "-"), ("peer", "-", ep(41))
        elif topology == "2 routers, clients":
            procs.append(spawn("router", ep(40), "1" if shm else "0", stdin=subprocess.PIPE))
            procs.append(spawn("router", ep(42), "1" if shm else "0", ep(40), stdin=subprocess.PIPE))
            time.sleep(1.5)
            sub_args, pub_args = ("client", "-", ep(40)), ("client", "-", ep(42))
        else:
            procs.append(spawn("router", ep(40), "1" if shm else "0", stdin=subprocess.PIPE))
            time.sleep(1.0)
            sub_args, pub_args = ("client", "-", ep(40)), ("client", "-", ep(40))
        out = measure(sub_args, pub_args, shm, size, n, rate)
        for p in procs:
            p.stdin.close()
            p.wait(timeout=30)
        load = open("/proc/loadavg").read().split()[0]
        print(f"{size:>9} B  {topology:<18} shm={'on ' if shm else 'off'}  {out}  load1={load}", flush=True)
        return json.loads(out)["p50_us"] if out else None


#: where a robot-local edge's two sessions (both on the robot) meet: direct (peers, the link a
#: deployment without --router uses; with and without shared memory), through a plain router on
#: the robot linked to the remote one (without shared memory, as the run routers of
#: ``retriever worker --local-router`` were when they were sessions of the daemon; and with it),
#: through Retriever's own run router (daemon/run_router.py: a process of the run's, with shared
#: memory, linked to a ``retriever router``), through the remote router (--router alone)
ROBOT_TOPOLOGIES = ("direct peers", "direct peers, shm", "local router", "local router, shm", "run router",
                    "remote router")
ROBOT_SIZES = [(64, 300, 100), (1 << 20, 300, 50)]
#: the lab's subnet: not the tests' (tests/deploy/lab.py), so that both can run at once
ROBOT_SUBNET = "10.200.79.0/24"
#: the namespace and run of the run router the probe opens
PROBE_NAMESPACE, PROBE_RUN = "default", "probe"


def run_router(secret_file: str, upstream: str) -> None:
    """``role runrouter``: open Retriever's router for run PROBE_RUN, linked to the ``retriever
    router`` at ``upstream`` as a worker daemon would (its Zenoh id asked with the namespace's
    password), print its endpoint, and close it when stdin closes."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from retriever.backends.zenoh.access import RunAccess, read_secret
    from retriever.backends.zenoh.daemon.run_router import open_run_router
    from retriever.backends.zenoh.hub import client_config

    secret = read_secret(secret_file)
    daemon = RunAccess.create(PROBE_NAMESPACE, secret).client_config(PROBE_NAMESPACE)
    with zenoh.open(client_config(connect=[upstream], access=daemon, shared_memory=False)) as session:
        ids = [str(z) for z in session.info.routers_zid()]
    router = open_run_router(PROBE_NAMESPACE, secret, PROBE_RUN, (upstream,), ids)
    print(router.endpoint, flush=True)
    sys.stdin.read()
    router.close()


def retriever_router(host, at: str, secret_file: str) -> subprocess.Popen:
    """``retriever router`` on ``host`` at ``at``, once it listens."""
    proc = host.popen([sys.executable, "-m", "retriever.cli", "router", "--listen", at, "--secret", secret_file],
                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    line = proc.stderr.readline()
    if not line.startswith("retriever router listening on"):
        raise RuntimeError(f"retriever router did not start: {line}{proc.stderr.read()}")
    return proc


def robot() -> None:
    """ROBOT_TOPOLOGIES in the netns lab: a router host, and a robot host behind NAT whose
    publisher and subscriber talk; each topology's median against the direct peers' (shm off)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests.deploy from this checkout
    from retriever.backends.zenoh.access import RunAccess, read_secret
    from retriever.backends.zenoh.wire import KeySpace
    from tests.deploy.lab import Lab

    with Lab(2, subnet=ROBOT_SUBNET) as lab, tempfile.TemporaryDirectory() as folder:
        hub, robot_host = lab.hosts
        lab.nat(robot_host)
        secret_file = Path(folder) / "probe.key"
        secret_file.write_text(os.urandom(32).hex() + "\n")
        secret_file.chmod(0o600)
        remote, local = f"tcp/{hub.address}:{BASE_PORT + 40}", ep(42)
        routers = [spawn("router", remote, "0", stdin=subprocess.PIPE, host=hub)]
        upstream = f"tcp/{hub.address}:{BASE_PORT + 44}"
        retriever_router(hub, upstream, str(secret_file))
        time.sleep(1.5)
        routers.append(spawn("router", local, "0", remote, stdin=subprocess.PIPE, host=robot_host))
        routers.append(spawn("router", ep(43), "1", remote, stdin=subprocess.PIPE, host=robot_host))
        routers.append(spawn("runrouter", str(secret_file), upstream, stdin=subprocess.PIPE, host=robot_host))
        run_at = routers[-1].stdout.readline().strip()
        flows = {"PROBE_ACCESS": json.dumps(RunAccess.create(PROBE_NAMESPACE, read_secret(secret_file), run=PROBE_RUN)
                                            .client_config(PROBE_NAMESPACE)),  # the run's flows' passwords
                 "PROBE_KEY": KeySpace(PROBE_NAMESPACE).data("camera", "frame")}
        time.sleep(1.5)
        pairs = {"direct peers": (("peer", ep(41), "-"), ("peer", "-", ep(41)), False),
                 "direct peers, shm": (("peer", ep(41), "-"), ("peer", "-", ep(41)), True),
                 "local router": (("client", "-", local), ("client", "-", local), False),
                 "local router, shm": (("client", "-", ep(43)), ("client", "-", ep(43)), True),
                 "run router": (("client", "-", run_at), ("client", "-", run_at), True),
                 "remote router": (("client", "-", remote), ("client", "-", remote), False)}
        medians: dict[tuple[int, str], float | None] = {}
        try:
            for size, n, rate in ROBOT_SIZES:
                for topology in ROBOT_TOPOLOGIES:
                    sub_args, pub_args, shm = pairs[topology]
                    out = measure(sub_args, pub_args, shm, size, n, rate, host=robot_host,
                                  env=flows if topology == "run router" else None)
                    load = open("/proc/loadavg").read().split()[0]
                    print(f"{size:>9} B  {topology:<18} {out}  load1={load}", flush=True)
                    medians[(size, topology)] = json.loads(out)["p50_us"] if out else None
        finally:
            for p in routers:
                p.stdin.close()
                p.wait(timeout=30)
            lab.stop_processes()
            lab.unnat(robot_host)
    print("\nmedian / direct peers' median, shm off (same run):", flush=True)
    for (size, topology), p50 in medians.items():
        direct = medians.get((size, "direct peers"))
        if topology != "direct peers" and direct and p50:
            print(f"{size:>9} B  {topology:<18} {p50 / direct:5.2f}x  ({p50 - direct:+,.0f} us)", flush=True)


#: as Retriever's peers (hub.GOSSIP_ONE_WAY): of two peers, only the one of greater id opens their link
GOSSIP_ONE_WAY = {"scouting/gossip/autoconnect_strategy": '{peer: {to_peer: "greater-zid", to_router: "always"}}'}


def links(n: int, mode: str) -> None:
    """``n`` sessions in this process joined through one router (clients) or one router plus the
    peers' gossip mesh (peers): the time until one put of session 0 reaches every session, and the
    links (TCP connections) that took."""
    hits = [0] * n
    router = zenoh.open(config("router", listen=[ep(50)]))
    t0 = time.monotonic()
    sessions = []
    try:
        for i in range(n):
            listen = [ep(60 + i)] if mode == "peer" else []
            sessions.append(zenoh.open(config(mode, listen=listen, connect=[ep(50)], extra=GOSSIP_ONE_WAY)))
        opened = time.monotonic() - t0
        subs = [s.declare_subscriber("links/all", lambda _, i=i: hits.__setitem__(i, hits[i] + 1))
                for i, s in enumerate(sessions)]
        while not all(hits) and time.monotonic() - t0 < 120:
            sessions[0].put("links/all", b"x")
            time.sleep(0.02)
        ready = time.monotonic() - t0
        time.sleep(2.0)  # the gossip mesh settles
        peer_links = sum(len(list(s.info.peers_zid())) for s in sessions) // 2
        router_links = len(list(router.info.transports()))
        tcp = subprocess.run(["ss", "-tnH", "state", "established"], capture_output=True, text=True).stdout
        ports = {str(BASE_PORT + 50)} | {str(BASE_PORT + 60 + i) for i in range(n)}
        accepted = sum(1 for line in tcp.splitlines() if line.split()[2].rsplit(":", 1)[1] in ports)
        threads = len(os.listdir("/proc/self/task"))
        rss = int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") >> 20
        print(f"{n:>4} {mode:<6}  opened {opened:6.2f} s  all reached {ready:6.2f} s  "
              f"links: to router {router_links}, peer-peer {peer_links}, accepted TCP {accepted}  "
              f"missing {hits.count(0)}  threads {threads}  RSS {rss} MiB  load1={open('/proc/loadavg').read().split()[0]}", flush=True)
        for sub in subs:
            sub.undeclare()
    finally:
        for s in sessions:
            s.close()
        router.close()


if __name__ == "__main__":
    {"functions": lambda: functions(), "tls": lambda: tls(sys.argv[2]), "latency": lambda: latency(sys.argv[2:]),
     "role": lambda: role(sys.argv[2:]), "links": lambda: links(int(sys.argv[2]), sys.argv[3]),
     "robot": lambda: robot()}[sys.argv[1]]()
