"""The ``retriever`` command, run as users run it: a subprocess of the installed console script."""

from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from retriever import IR, Pipeline

ROOT = Path(__file__).resolve().parent.parent
QUICKSTART = ROOT / "examples" / "quickstart.py"
GOLDEN = Path(__file__).parent / "golden"
RETRIEVER = Path(sys.executable).parent / "retriever"


def cli(*args: str, cwd: Path | None = None, pythonpath: Path | None = None,
        columns: int = 200) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    env.update(NO_COLOR="1", TERM="dumb", COLUMNS=str(columns), PYTHONIOENCODING="utf-8")
    # this checkout's retriever, not whichever one the venv's editable install points at
    env["PYTHONPATH"] = os.pathsep.join(str(p) for p in (pythonpath, ROOT) if p is not None)
    return subprocess.run([str(RETRIEVER), *args], capture_output=True, text=True, cwd=cwd or ROOT, env=env,
                          timeout=120)


@functools.cache
def quickstart_ir(fmt: str) -> str:
    """``retriever ir examples/quickstart.py --format FMT`` (stdout), run once per format."""
    result = cli("ir", str(QUICKSTART), "--format", fmt)
    assert result.returncode == 0, result.stderr
    return result.stdout


def assert_cli_error(result: subprocess.CompletedProcess, message: str, hint: str | None = None) -> None:
    """Exit status non-zero, ``error: …`` first on stderr, an optional ``hint: …`` (indented under
    its item when the error lists several problems), no traceback."""
    assert result.returncode != 0, result
    assert result.stderr.startswith("error: "), result.stderr
    assert re.search(message, result.stderr, re.MULTILINE), result.stderr
    if hint is not None:
        assert re.search(r"^(    )?hint: " + hint, result.stderr, re.MULTILINE), result.stderr
    assert "Traceback" not in result.stderr
    assert "Traceback" not in result.stdout


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


FLOWS = '''
from retriever import Flow, Pipeline, Rate, Trigger, io


@io
class Num:
    x: int


class Source(Flow[None, Num]):
    def step(self, inp):
        return Num(1)


class Sink(Flow[Num, None]):
    def step(self, inp):
        return None
'''


# ---------------------------------------------------------------------------------------------
# retriever run
# ---------------------------------------------------------------------------------------------
def test_run_until_stopped_prints_its_table_when_interrupted(tmp_path: Path):
    """`--duration inf` runs until Ctrl-C; the interrupted run still shows its table and counters
    (not only "interrupted")."""
    import signal
    import time

    log = tmp_path / "run.mcap"
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    env.update(NO_COLOR="1", TERM="dumb", COLUMNS="200", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([str(RETRIEVER), "run", str(QUICKSTART), "--duration", "inf", "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    try:
        give_up = time.monotonic() + 60  # a bound: the log is created as the run starts
        while not (log.exists() and log.stat().st_size > 0) and time.monotonic() < give_up:
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "quickstart: until stopped on inproc, interrupted" in out, out
    assert re.search(r"camera\s+│\s+\d+", out) and "trace digest" in out, out
    assert f"interrupted; the run so far is in {log}" in err, err


LINK_SEEING = FLOWS + '''
import glob, os, tempfile


class Seeing(Flow[Num, None]):
    """Writes down the same-host link sockets in its run's folder (its parent's, the coordinator's)."""

    def step(self, inp):
        folders = {"/dev/shm", tempfile.gettempdir()}
        found = [os.path.basename(p) for base in folders
                 for p in glob.glob(f"{base}/retriever-run-{os.getppid()}-*/link-*.sock")]
        with open("seen.txt", "a") as f:
            f.write(" ".join(sorted(found)) + "\\n")


with Pipeline("seeing") as pipe:
    (Source().named("source") @ Rate(hz=20)).then(Seeing().named("seeing") @ Trigger())
'''


@pytest.mark.parametrize("option, sockets", [((), {"link-source.sock"}), (("--no-links",), {""})])
def test_run_no_links_carries_every_edge_on_zenoh(tmp_path: Path, option, sockets):
    """`retriever run --backend zenoh` carries an edge between two of its processes over a
    same-host link (the producer's socket in the run's folder); `--no-links` keeps it on Zenoh."""
    (tmp_path / "seeing.py").write_text(LINK_SEEING)
    result = cli("run", "seeing.py:pipe", "--duration", "0.5", "--backend", "zenoh", *option, cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    seen = (tmp_path / "seen.txt").read_text().splitlines()
    assert seen and set(seen) == sockets, seen


def test_run_no_links_is_for_zenoh_only(tmp_path: Path):
    assert_cli_error(cli("run", str(QUICKSTART), "--no-links"),
                     r"^error: --no-links is for --backend zenoh \(only its runs have same-host links\)$",
                     hint=r"retriever run FILE --backend zenoh --no-links, or drop --no-links")


@pytest.mark.parametrize("signum", [15, 2])  # SIGTERM, SIGINT
def test_a_signal_that_lands_in_an_exec_still_ends_with_the_status_the_command_chose(tmp_path: Path, signum):
    """A stop signal that came while an exec() of a string ran (rosbags making a message class,
    a dataclass being made): CPython takes a bare KeyboardInterrupt leaving it as unhandled, even
    once caught, and ended a ``python -m`` process (as ``retriever`` is) by SIGINT (-2), not with
    the command's 128 + the signal. An export stopped by SIGTERM exited -2 so, in CI."""
    (tmp_path / "stopped.py").write_text(
        "import os, sys\n"
        "from retriever.cli import stop_on_signals, stop_signal\n"
        "stop_on_signals()\n"
        "try:\n"
        f"    exec('os.kill(os.getpid(), {signum})\\nfor _ in range(10**7): pass')\n"
        "except KeyboardInterrupt:\n"
        "    sys.exit(128 + stop_signal())\n"
        "sys.exit('the signal never came')\n")
    done = subprocess.run([sys.executable, "-m", "stopped"], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 128 + signum, (done.returncode, done.stderr)


def test_a_command_started_with_sigint_ignored_keeps_ignoring_it(tmp_path: Path):
    """A shell's background job starts with SIGINT ignored (the terminal's Ctrl-C is for the
    foreground): taking SIGTERM as Ctrl-C must not make it take Ctrl-C again."""
    (tmp_path / "ignoring.py").write_text(
        "import os, signal, sys\n"
        "from retriever.cli import stop_on_signals\n"
        "stop_on_signals()\n"
        "os.kill(os.getpid(), signal.SIGINT)\n"
        "sys.exit(0 if signal.getsignal(signal.SIGINT) is signal.SIG_IGN else 'SIGINT is no longer ignored')\n")
    done = subprocess.run([sys.executable, "-m", "ignoring"], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=lambda: signal.signal(signal.SIGINT,
                                                                                                       signal.SIG_IGN))
    assert done.returncode == 0, (done.returncode, done.stderr)


@pytest.mark.parametrize("first, second", [(15, 15), (2, 2), (15, 2), (2, 15)])
def test_a_second_stop_signal_during_the_clean_up_changes_nothing_and_a_third_ends_at_once(tmp_path: Path, first,
                                                                                            second):
    """Ctrl-C pressed twice, or SIGTERM then Ctrl-C: the second signal comes while the command
    cleans up after the first (an export removing its half-written file, a run printing its table)
    or while the interpreter ends. Raised there it cut the clean-up short, or printed "Exception
    ignored in: <module 'threading'> ... Interrupted" after the command's one line: it is ignored.
    A third means the clean-up hangs: the process ends at once, by the signal."""
    script = (
        "import os, sys, threading\n"
        "from retriever.cli import cleaning_up, stop_on_signals, stop_signal\n"
        "stop_on_signals()\n"
        "threading.Thread(target=lambda: None).start()  # as a run's: threading._shutdown runs at exit\n"
        "try:\n"
        f"    os.kill(os.getpid(), {first})\n"
        "    for _ in range(10**7): pass\n"
        "    sys.exit('the first signal never came')\n"
        "except KeyboardInterrupt:\n"
        "    cleaning_up()\n"
        f"    os.kill(os.getpid(), {second})  # handled at the next instruction, in the clean-up\n"
        "    for _ in range(1000): pass\n"
        "    if len(sys.argv) > 1:\n"
        f"        os.kill(os.getpid(), {first})\n"
        "        for _ in range(10**7): pass\n"
        "        sys.exit('the third signal did not end it')\n"
        "    print('cleaned up', file=sys.stderr)\n"
        "    sys.exit(128 + stop_signal())\n")
    (tmp_path / "twice.py").write_text(script)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    twice = subprocess.run([sys.executable, "-m", "twice"], capture_output=True, text=True, timeout=120,
                           cwd=tmp_path, env=env)
    assert (twice.returncode, twice.stderr) == (128 + first, "cleaned up\n")
    thrice = subprocess.run([sys.executable, "-m", "twice", "thrice"], capture_output=True, text=True, timeout=120,
                            cwd=tmp_path, env=env)
    assert (thrice.returncode, thrice.stderr) == (-first, "")


def test_a_signal_a_logged_run_ignored_as_its_log_ended_counts_for_the_command_too(tmp_path: Path):
    """A logged run ignores a second signal while it writes its log's end; the command's clean-up
    then counts it (``cleaning_up(ignored_one=True)``): the next signal ends the process at once,
    not a fourth."""
    (tmp_path / "counted.py").write_text(
        "import os, sys\n"
        "from retriever.cli import cleaning_up, stop_on_signals\n"
        "stop_on_signals()\n"
        "cleaning_up(ignored_one=True)\n"
        "os.kill(os.getpid(), 2)\n"
        "for _ in range(10**7): pass\n"
        "sys.exit('the signal did not end it')\n")
    done = subprocess.run([sys.executable, "-m", "counted"], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert (done.returncode, done.stderr) == (-2, "")


STOPPED_INSIDE = FLOWS + '''

import os, signal


class Dropping:
    """Sends the signal from its __del__, where Python drops an exception (the handler's)."""
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000): pass


class DropsTheStop(Flow[None, Num]):
    dropped = False

    def step(self, inp):
        if not self.dropped:
            self.dropped = True
            Dropping()
        return Num(1)


class FailsWithTheStop(Flow[None, Num]):
    def setup(self):
        try:  # as a C extension whose import the signal interrupts: ImportError, not the signal
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(10**7): pass
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None

    def step(self, inp):
        return Num(1)


with Pipeline("dropped") as dropped:
    (DropsTheStop() @ Rate(hz=10)).then(Sink() @ Trigger())
with Pipeline("failed") as failed:
    (FailsWithTheStop() @ Rate(hz=10)).then(Sink() @ Trigger())
'''


@pytest.mark.parametrize("pipe", ["dropped", "failed"])
def test_a_run_whose_stop_signal_was_dropped_or_turned_into_an_error_still_ends_interrupted(tmp_path: Path, pipe):
    """SIGTERM's exception raised where Python drops it (a __del__: "Exception ignored in") let
    the run go on and exit 0; one that a setup() turned into another error (a C extension's
    import interrupted says ImportError) was reported as that setup's failure. The command was
    stopped by a signal: it says "interrupted" and exits 143."""
    path = write(tmp_path / "stopped.py", STOPPED_INSIDE)
    result = cli("run", f"{path}:{pipe}", "--duration", "2")
    assert result.returncode == 143, (result.returncode, result.stderr)
    assert result.stderr.rstrip().endswith("interrupted"), result.stderr
    assert "error:" not in result.stderr


def test_version_as_a_flag_and_python_dash_m():
    from importlib import metadata

    from retriever.log.format import DISTRIBUTION

    expected = f"retriever {metadata.version(DISTRIBUTION)}\n"
    assert cli("--version").stdout == expected
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"PYTHONPATH": str(ROOT), "NO_COLOR": "1"}
    done = subprocess.run([sys.executable, "-m", "retriever", "--version"], capture_output=True, text=True,
                          env=env, timeout=60)
    assert done.returncode == 0 and done.stdout == expected, done.stderr


def test_the_package_says_it_is_typed():
    assert (ROOT / "retriever" / "py.typed").exists()
    assert '"py.typed"' in (ROOT / "pyproject.toml").read_text()


def test_run_prints_a_table_with_every_node():
    result = cli("run", str(QUICKSTART), "--backend", "inproc", "--duration", "1")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "quickstart: 1 s on inproc" in out
    assert re.search(r"node\s*┃\s*ticks\s*┃\s*steps\s*┃\s*skips\s*┃\s*errors\s*┃\s*mean step", out), out
    rows = dict(re.findall(r"│ (\w+)\s*│\s*(\d+ │\s*\d+ │\s*\d+ │\s*\d+) │\s*[\d.]+ [µm]s │", out))
    assert set(rows) == {"camera", "policy", "controller"}, out
    ticks = {node: [int(n) for n in re.findall(r"\d+", row)] for node, row in rows.items()}
    assert ticks["camera"] == [30, 30, 0, 0]
    assert ticks["controller"][0] == 200
    assert ticks["policy"][0] == 2
    assert all(t == s + k + e for t, s, k, e in ticks.values())
    assert re.search(r"\d+ events · \d+ steps · trace digest [0-9a-f]{16}", out)
    assert result.stderr == ""


def test_run_on_an_80_column_terminal_shows_long_node_names_whole(tmp_path: Path):
    """A table is as wide as its content, past the terminal's edge if it must be: a node name cut
    to fit (`contro…`) names nothing."""
    long = "a_controller_with_a_rather_long_name_for_its_left_arm"
    write(tmp_path / "long.py", FLOWS + f"""
with Pipeline("long") as pipe:
    (Source().named("{long}_source") @ Rate(hz=10)).then(Sink().named("{long}") @ Trigger())
""")
    log = f"{long}.mcap"
    result = cli("run", "long.py", "--backend", "inproc", "--duration", "1", "--log", log, cwd=tmp_path, columns=80)
    assert result.returncode == 0, result.stderr
    assert re.search(rf"│ {long}\s+│\s+10 │\s+10 │\s+0 │\s+0 │", result.stdout), result.stdout
    assert f"│ {long}_source " in result.stdout and "…" not in result.stdout, result.stdout
    assert f"check it with: retriever replay {log}\n" in result.stdout, result.stdout  # a command, whole


def test_run_digest_is_the_in_process_digest():
    from retriever.loading import load_pipeline

    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()
    expected = pipe.run(duration=0.5).digest()[:16]
    result = cli("run", str(QUICKSTART), "--duration", "0.5")
    assert result.returncode == 0, result.stderr
    assert f"trace digest {expected}" in result.stdout


def test_run_file_colon_attr():
    result = cli("run", f"{QUICKSTART}:pipe", "--duration", "0.1")
    assert result.returncode == 0, result.stderr
    assert "quickstart: 0.1 s on inproc" in result.stdout


def test_run_a_module_of_a_package_by_its_file(tmp_path: Path):
    """A file in a package (its folder has __init__.py) is imported by its dotted name, so its
    relative imports work: retriever run app/agent.py runs app.agent."""
    package = tmp_path / "app"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "flows.py").write_text(
        "from retriever import Flow\n"
        "class Count(Flow):\n"
        "    def __init__(self):\n        self.n = 0\n"
        "    def step(self):\n        self.n += 1\n        return {'n': self.n}\n")
    (package / "agent.py").write_text(
        "from retriever import Pipeline, Rate\nfrom .flows import Count\n"
        "with Pipeline('packaged') as pipe:\n    Count().named('count') @ Rate(10)\n")
    result = cli("run", str(package / "agent.py"), "--duration", "1", cwd=tmp_path.parent)
    assert result.returncode == 0, result.stderr
    assert "packaged: 1 s on inproc" in result.stdout


def test_run_an_ir_file(tmp_path: Path):
    from tests import ir_flows

    pipe = ir_flows.build()
    path = pipe.build_ir().save(tmp_path / "small.ir.json")
    expected = pipe.run(duration=2.0).digest()[:16]
    result = cli("run", str(path), "--duration", "2", pythonpath=ROOT)
    assert result.returncode == 0, result.stderr
    for node in ("camera", "planner", "controller", "logger"):
        assert f"│ {node} " in result.stdout
    assert f"trace digest {expected}" in result.stdout


SCRIPT_FLOWS = FLOWS + '''

with Pipeline("scripted") as pipe:
    (Source() @ Rate(hz=10)).then(Sink() @ Trigger())
'''


def test_run_an_ir_saved_from_a_script_from_anywhere(tmp_path: Path):
    """The IR records the folder of a script's flows (metadata.module_folders): "No module named
    'quickstart'" was the answer even inside the script's folder."""
    (tmp_path / "project").mkdir()
    (tmp_path / "elsewhere").mkdir()
    script = write(tmp_path / "project" / "scripted.py", SCRIPT_FLOWS)
    saved = tmp_path / "elsewhere" / "scripted.ir.json"
    built = cli("ir", str(script), "--out", str(saved), pythonpath=ROOT)
    assert built.returncode == 0, built.stderr
    assert json.loads(saved.read_text())["metadata"]["module_folders"] == {"scripted": str(tmp_path / "project")}
    for cwd in (tmp_path, tmp_path / "elsewhere", tmp_path / "project"):
        result = cli("run", str(saved), "--duration", "1", cwd=cwd, pythonpath=ROOT)
        assert result.returncode == 0, result.stderr
        assert "│ source " in result.stdout and "│ sink " in result.stdout


def test_run_an_ir_beside_its_script_or_from_its_folder(tmp_path: Path):
    """Without the recorded folder (an IR of 1.1.0, or one moved to another machine), the IR file's
    folder and the working directory are on the import path."""
    script = write(tmp_path / "scripted.py", SCRIPT_FLOWS)
    built = cli("ir", str(script), "--out", str(tmp_path / "beside.ir.json"), pythonpath=ROOT)
    assert built.returncode == 0, built.stderr
    doc = json.loads((tmp_path / "beside.ir.json").read_text())
    del doc["metadata"]["module_folders"]
    write(tmp_path / "beside.ir.json", json.dumps(doc))
    (tmp_path / "sub").mkdir()
    write(tmp_path / "sub" / "below.ir.json", json.dumps(doc))
    failed = cli("run", "below.ir.json", "--duration", "1", cwd=tmp_path / "sub", pythonpath=ROOT)
    assert failed.returncode == 1 and "No module named 'scripted'" in failed.stderr, failed.stderr
    for cwd, target in ((tmp_path / "sub", "../beside.ir.json"), (tmp_path, "sub/below.ir.json")):
        result = cli("run", target, "--duration", "1", cwd=cwd, pythonpath=ROOT)
        assert result.returncode == 0, result.stderr


def test_run_an_ir_whose_flows_cannot_be_found_names_the_folder(tmp_path: Path):
    script = write(tmp_path / "scripted.py", SCRIPT_FLOWS)
    saved = tmp_path / "elsewhere.ir.json"
    assert cli("ir", str(script), "--out", str(saved), pythonpath=ROOT).returncode == 0
    doc = json.loads(saved.read_text())
    doc["metadata"]["module_folders"] = {"scripted": "/gone/project"}
    (tmp_path / "other").mkdir()
    write(tmp_path / "other" / "moved.ir.json", json.dumps(doc))
    result = cli("run", "moved.ir.json", "--duration", "1", cwd=tmp_path / "other", pythonpath=ROOT)
    assert_cli_error(result, r"^  - node 'source': cannot import scripted:Source \(No module named 'scripted'\)$",
                     hint=r"the IR was built with it from /gone/project: run there, or PYTHONPATH=/gone/project$")


def test_run_unknown_backend():
    result = cli("run", str(QUICKSTART), "--backend", "ros2", "--duration", "1")
    assert_cli_error(result, r"^error: unknown backend 'ros2'; available: dora, inproc, zenoh$")


def test_run_a_step_that_raises(tmp_path: Path):
    script = write(tmp_path / "failing.py", FLOWS + '''

class Broken(Flow[None, Num]):
    def step(self, inp):
        return Num(1 // 0)


with Pipeline("failing") as pipe:
    Broken() @ Rate(hz=10)
''')
    result = cli("run", str(script), "--duration", "1")
    assert_cli_error(result, r"^error: broken\.step\(\) raised ZeroDivisionError: integer division or modulo by zero "
                             r"\(tick at t=0\.000000000s m=0\)", hint=r"set on_error='skip_tick' or 'restart'")


def test_run_a_step_that_calls_sys_exit(tmp_path: Path):
    """It exited silently with the step's status (3) before."""
    script = write(tmp_path / "exiting.py", FLOWS + '''
import sys


class Exiting(Flow[None, Num]):
    def step(self, inp):
        sys.exit(3)


with Pipeline("exiting") as pipe:
    Exiting() @ Rate(hz=10)
''')
    result = cli("run", str(script), "--duration", "1", pythonpath=ROOT)
    assert result.returncode == 1
    assert_cli_error(result, r"^error: exiting\.step\(\) raised SystemExit: 3 \(tick at t=0\.000000000s m=0\)",
                     hint=r"set on_error='skip_tick' or 'restart'")


def test_run_a_step_returning_an_unencodable_value(tmp_path: Path):
    """It ran to the end, then died with a traceback in trace.digest() before."""
    script = write(tmp_path / "locking.py", FLOWS + '''
import threading


class Locking(Flow):
    def step(self):
        return {"lock": threading.Lock()}


with Pipeline("locking") as pipe:
    Locking() @ Rate(hz=10)
''')
    result = cli("run", str(script), "--duration", "1", pythonpath=ROOT)
    assert_cli_error(result, r"^error: locking\.lock: the step at t=0\.000000000s m=0 returned a value the run cannot "
                             r"record: cannot encode a value of type _thread\.lock$",
                     hint=r"use numbers, str, bytes, lists, dicts, numpy arrays or @io dataclasses")


ZENO = '''
from retriever import Flow, Pipeline, Rate, Trigger


class Relay(Flow):
    def step(self, a=None):
        return {"a": 1}


with Pipeline("zeno", max_microsteps=10) as pipe:
    a, b = Relay() @ Trigger("a"), Relay() @ Trigger("a")
    a.then(b).then(a)
    (Relay() @ Rate(hz=1)).then(a)
'''


def test_run_a_zeno_loop(tmp_path: Path):
    script = write(tmp_path / "zeno.py", ZENO)
    result = cli("run", str(script), "--duration", "1")
    assert result.returncode != 0
    assert re.search(r"^error: Zeno loop: the instant at t=0\.000000000s m=\d+ ran past max_microsteps=10 around the "
                     r"cycle relay(_2)? → relay(_2)? → relay(_2)?\nhint: break the cycle in time", result.stderr,
                     re.MULTILINE), result.stderr
    assert "Traceback" not in result.stderr


def test_build_warnings_print_as_warning_lines(tmp_path: Path):
    script = write(tmp_path / "zeno.py", ZENO)
    result = cli("ir", str(script))
    assert result.returncode == 0, result.stderr
    # a RetrieverWarning is user-facing text like an error: "warning: …", not Python's
    # "path/to/retriever/pipeline.py:169: RetrieverWarning: …" followed by a source line
    assert result.stderr.startswith("warning: pipeline 'zeno': instantaneous cycle relay → relay_2 → relay"), \
        result.stderr
    assert "RetrieverWarning" not in result.stderr
    assert ".py:" not in result.stderr


# ---------------------------------------------------------------------------------------------
# retriever ir
# ---------------------------------------------------------------------------------------------
def test_ir_json_by_default():
    result = cli("ir", str(QUICKSTART))
    assert result.returncode == 0, result.stderr
    assert result.stdout == quickstart_ir("json")
    doc = json.loads(result.stdout)
    assert doc["version"] == "1.4.0"
    assert doc["metadata"]["name"] == "quickstart"
    assert [n["id"] for n in doc["nodes"]] == ["camera", "policy", "controller"]
    assert [n["type"] for n in doc["nodes"]] == ["quickstart:Camera", "quickstart:Policy", "quickstart:Controller"]
    assert IR(doc).to_json() == result.stdout


def test_ir_json_is_the_library_json():
    from retriever.loading import load_pipeline

    expected = load_pipeline(str(QUICKSTART)).build_ir().to_json()
    assert quickstart_ir("json") == expected


def test_ir_of_an_ir_file_or_a_log_draws_the_graph_without_importing_anything(tmp_path: Path):
    """issue 19 §5: an IR file or a log is read and checked, never imported: the modules its
    nodes name could be anything (here one that would leave a marker file if imported)."""
    doc = json.loads(quickstart_ir("json"))
    (tmp_path / "planted.py").write_text("import pathlib\npathlib.Path('imported').write_text('x')\n")
    for node in doc["nodes"]:
        node["type"] = node["type"].replace("quickstart:", "planted:")
    ir_file = tmp_path / "q.ir.json"
    ir_file.write_text(json.dumps(doc))
    drawn = cli("ir", str(ir_file), "--format", "dot", cwd=tmp_path, pythonpath=tmp_path)
    assert drawn.returncode == 0, drawn.stderr
    assert drawn.stdout == quickstart_ir("dot")
    assert not (tmp_path / "imported").exists(), "retriever ir imported a module the IR names"

    log = tmp_path / "run.mcap"
    assert cli("run", str(QUICKSTART), "--duration", "0.5", "--log", str(log)).returncode == 0
    elsewhere = tmp_path / "elsewhere"  # where quickstart is not importable
    elsewhere.mkdir()
    drawn = cli("ir", str(log), "--format", "mermaid", cwd=elsewhere)
    assert drawn.returncode == 0, drawn.stderr
    assert drawn.stdout == quickstart_ir("mermaid")


@pytest.mark.parametrize("fmt, node_text, edge_text", [
    ("dot", '"{node}" [label=', '"{src}" -> "{dst}"'),
    ("mermaid", '  {node}["{node}<br/>', "  {src} -->|"),
])
def test_ir_pictures_contain_every_node_and_edge(fmt, node_text, edge_text):
    text = quickstart_ir(fmt)
    for node in ("camera", "policy", "controller"):
        assert node_text.format(node=node) in text
    for src, dst in (("camera", "policy"), ("policy", "controller"), ("controller", "policy")):
        assert edge_text.format(src=src, dst=dst) in text
    assert text.count("-->" if fmt == "mermaid" else " -> ") == 3
    # the policy's LET latency, in both pictures (Mermaid's lacked it)
    assert ("policy<br/>Rate 2 Hz<br/>latency 0.3 s" if fmt == "mermaid" else "latency 0.3 s") in text, text
    if fmt == "mermaid":
        assert text.startswith("flowchart LR\n")
    else:
        assert text.startswith('digraph "quickstart" {')


@pytest.mark.parametrize("fmt", ["json", "dot", "mermaid"])
def test_ir_out_writes_the_file(tmp_path: Path, fmt: str):
    out = tmp_path / f"quickstart.{fmt}"
    result = cli("ir", f"{QUICKSTART}:pipe", "--format", fmt, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    assert result.stderr.strip() == f"wrote {out}"
    assert out.read_text(encoding="utf-8") == quickstart_ir(fmt)


def test_ir_out_json_loads_back(tmp_path: Path):
    out = tmp_path / "quickstart.ir.json"
    assert cli("ir", str(QUICKSTART), "-o", str(out)).returncode == 0
    assert IR.load(out).name == "quickstart"


def test_ir_unknown_format():
    result = cli("ir", str(QUICKSTART), "--format", "svg")
    assert_cli_error(result, r"^error: unknown format 'svg'$", hint=r"use --format json, dot or mermaid")


# ---------------------------------------------------------------------------------------------
# Errors loading FILE[:ATTR]
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["run", "ir"])
def test_missing_file(command: str):
    result = cli(command, "no/such/file.py")
    assert_cli_error(result, r"^error: no such file: no/such/file\.py$",
                     hint=r"give a Python file defining a Pipeline, e\.g\. retriever run examples/quickstart\.py")


def test_file_without_a_pipeline(tmp_path: Path):
    write(tmp_path / "empty.py", FLOWS)
    result = cli("run", "empty.py", cwd=tmp_path)
    assert_cli_error(result, r"^error: empty\.py defines no Pipeline at module level$",
                     hint=r"build it at module level: with Pipeline\(\"name\"\) as pipe: \.\.\.")


def test_cli_error_text_matches_golden_file(tmp_path: Path):
    write(tmp_path / "empty.py", FLOWS)
    result = cli("ir", "empty.py", cwd=tmp_path)
    golden = GOLDEN / "cli_no_pipeline.txt"
    if os.environ.get("RETRIEVER_UPDATE_GOLDEN") == "1":
        golden.write_text(result.stderr, encoding="utf-8")
    assert result.returncode == 1
    assert result.stdout == ""
    assert result.stderr == golden.read_text(encoding="utf-8")


def test_file_with_several_pipelines_hints_at_file_colon_attr(tmp_path: Path):
    write(tmp_path / "two.py", FLOWS + '''

with Pipeline("one") as first:
    Source() @ Rate(hz=1)

with Pipeline("two") as second:
    Source() @ Rate(hz=1)
''')
    result = cli("run", "two.py", cwd=tmp_path)
    assert_cli_error(result, r"^error: two\.py defines several Pipelines \(first, second\)$",
                     hint=r"name one: two\.py:first")
    ok = cli("run", "two.py:second", "--duration", "1", cwd=tmp_path)
    assert ok.returncode == 0, ok.stderr
    assert "two: 1 s on inproc" in ok.stdout


def test_file_colon_unknown_attr():
    result = cli("ir", f"{QUICKSTART}:nope")
    assert_cli_error(result, r"quickstart\.py has no Pipeline named 'nope' \(it has: pipe\)")


def test_file_with_a_graph_error(tmp_path: Path):
    write(tmp_path / "bad.py", FLOWS + '''

class NoStep(Flow[Num, None]):
    pass


with Pipeline("bad") as pipe:
    Source().then(NoStep() @ Trigger("y"))
''')
    for command in ("run", "ir"):
        result = cli(command, "bad.py", cwd=tmp_path)
        assert_cli_error(result, r"^error: pipeline 'bad' has 3 problems:\n"
                                 r"  - flow 'no_step' \(bad:NoStep\) has no step\(\) method\n",
                         hint=r"define step\(self, inp\)")
        assert "  - flow 'source' has no clock\n" in result.stderr
        assert "  - Trigger('y') on 'no_step': 'no_step' has no input port 'y' (inputs: x)\n" in result.stderr
        assert result.stderr.count("hint: ") == 3


def test_graph_error_hints_stay_under_their_problem(tmp_path: Path):
    write(tmp_path / "bad.py", FLOWS + '''

with Pipeline("bad") as pipe:
    Source().then(Sink() @ Trigger("y"))
''')
    result = cli("ir", "bad.py", cwd=tmp_path)
    lines = result.stderr.splitlines()
    assert lines[0] == "error: pipeline 'bad' has 2 problems:"
    # each hint belongs to the problem above it, so it is indented under that "  - " line
    assert lines[1].startswith("  - flow 'source' has no clock")
    assert lines[2].startswith("    hint: bind one"), result.stderr


def test_file_that_raises_while_importing(tmp_path: Path):
    write(tmp_path / "oops.py", "x = 1 / 0\n")
    result = cli("run", "oops.py", cwd=tmp_path)
    assert_cli_error(result, r"^error: ZeroDivisionError: division by zero\n\(run with --debug for the traceback\)")


@pytest.mark.parametrize("where", ["before the command", "after it"])
def test_debug_shows_the_traceback(tmp_path: Path, where):
    write(tmp_path / "oops.py", "x = 1 / 0\n")
    args = ["run", "oops.py", "--duration", "1"]
    result = cli(*(["--debug", *args] if where == "before the command" else [*args, "--debug"]), cwd=tmp_path)
    assert result.returncode != 0
    assert "Traceback (most recent call last)" in result.stderr
    assert "error: ZeroDivisionError: division by zero" in result.stderr


def test_debug_after_the_worker_command_shows_the_traceback(tmp_path: Path):
    """retriever-worker has no subcommand: --debug anywhere is its own."""
    worker = RETRIEVER.parent / "retriever-worker"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"PYTHONPATH": str(ROOT), "NO_COLOR": "1"}
    done = subprocess.run([str(worker), "--name", "w", "--config", str(tmp_path / "none.toml"), "--debug"],
                          capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 1 and "Traceback (most recent call last)" in done.stderr, done.stderr


def test_debug_shows_the_traceback_of_a_retriever_error():
    result = cli("--debug", "run", str(QUICKSTART), "--backend", "ros2")
    assert result.returncode != 0
    assert "Traceback (most recent call last)" in result.stderr
    assert "BackendError" in result.stderr
    assert "error: unknown backend 'ros2'" in result.stderr


def test_no_arguments_prints_help():
    result = cli()
    assert "run" in result.stdout + result.stderr
    assert "ir" in result.stdout + result.stderr
    assert "Traceback" not in result.stderr


def test_load_pipeline_in_process_matches_the_cli_target_syntax():
    from retriever.loading import load_pipeline

    pipe = load_pipeline(f"{QUICKSTART}:pipe")
    assert isinstance(pipe, Pipeline) and pipe.name == "quickstart"


FLAKY = '''
from retriever import Flow, Pipeline, Rate


class Flaky(Flow[None, int]):
    def __init__(self):
        self.k = 0

    def step(self, inp):
        self.k += 1
        if self.k == 2:
            raise ValueError("second call")
        return self.k


with Pipeline("flaky") as pipe:
    Flaky().configure(on_error="skip_tick") @ Rate(hz=10)
'''


def test_a_run_whose_errors_were_absorbed_exits_1_unless_allowed(tmp_path: Path):
    """on_error='skip_tick' lets the run go on; the run still had an error: the table, then
    error/hint and exit 1 (it exited 0), unless --allow-errors."""
    script = write(tmp_path / "flaky.py", FLAKY)
    result = cli("run", str(script), "--duration", "1", pythonpath=ROOT)
    assert_cli_error(result, r"^error: the run went on, but had errors \(flaky: 1 step error\(s\)\)$",
                     hint=r"the error records say what raised")
    assert re.search(r"^│ flaky +│ +10 │ +9 │ +0 │ +1 │", result.stdout, re.MULTILINE), result.stdout
    allowed = cli("run", str(script), "--duration", "1", "--allow-errors", pythonpath=ROOT)
    assert allowed.returncode == 0 and allowed.stderr == "", allowed.stderr


def test_a_node_moved_after_its_worker_was_lost_fails_the_run_as_a_restart_saying_it_moved():
    """A move (on_worker_loss) counts as a restart, by the same rule (exit 1 unless
    --allow-errors); the error says the node moved because its worker was lost, not a step
    error, and the hint names on_worker_loss beside --allow-errors (issue 38)."""
    from retriever.backends.base import NodeStats
    from retriever.cli import run_errors

    error = run_errors({"relay": NodeStats(counts={"moves": 1}), "sink": NodeStats()})
    message, hint = str(error).split("\n")
    assert message == ("the run went on, but had errors (relay: 1 restart(s) (moved because its worker was lost, "
                       "not a step error))")
    assert hint == ("    hint: 1 move(s) followed a lost worker: retriever log info LOG shows which worker ran each "
                    "node; pass --allow-errors when on_worker_loss='replace' or 'wait' is meant to absorb them")


def test_a_run_with_step_errors_crashes_and_a_move_names_each_and_both_policies():
    from retriever.backends.base import NodeStats
    from retriever.cli import run_errors

    error = run_errors({"flaky": NodeStats(errors=2, counts={"restarts": 2}),
                        "relay": NodeStats(counts={"restarts": 1, "crash_restarts": 1, "moves": 1})})
    message, hint = str(error).split("\n")
    assert message == ("the run went on, but had errors (flaky: 2 step error(s), 2 restart(s); relay: 2 restart(s) "
                       "(1 of them moved because its worker was lost, not a step error))")
    assert hint == ("    hint: the error records say what raised (retriever log cat LOG --steps); 1 restart(s) "
                    "followed a process that died: retriever log info LOG shows each fault; 1 move(s) followed a "
                    "lost worker: retriever log info LOG shows which worker ran each node; pass --allow-errors when "
                    "on_error='skip_tick' or 'restart' or on_worker_loss='replace' or 'wait' is meant to absorb them")
    assert run_errors({"calm": NodeStats(counts={"late": 3})}) is None


# ---------------------------------------------------------------------------------------------
# retriever secret new
# ---------------------------------------------------------------------------------------------
def secret_new(path: Path, *args: str) -> subprocess.CompletedProcess:
    """``retriever secret new PATH`` under a umask that would leave any file world-readable."""
    old = os.umask(0)  # the child inherits it
    try:
        return cli("secret", "new", str(path), *args)
    finally:
        os.umask(old)


def test_secret_new_writes_a_private_secret_that_run_takes(tmp_path: Path):
    key = tmp_path / "lab.key"
    result = secret_new(key)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"wrote a new deployment secret to {key} (32 random bytes as hex text, "
                                    f"mode 600)\n"), result.stdout
    assert f"use it: retriever run SCRIPT.py --backend zenoh --secret {key}" in result.stdout
    assert "every machine of the deployment needs this same file: copy it privately" in result.stdout
    assert key.stat().st_mode & 0o777 == 0o600
    assert len(key.read_text()) == 65
    run = cli("run", str(QUICKSTART), "--duration", "0.5", "--backend", "zenoh", "--secret", str(key))
    assert run.returncode == 0, run.stdout + run.stderr
    assert "quickstart: 0.5 s on zenoh" in run.stdout


def test_secret_new_keeps_an_existing_file_unless_forced(tmp_path: Path):
    key = tmp_path / "lab.key"
    assert secret_new(key).returncode == 0
    old = key.read_text()
    assert_cli_error(secret_new(key), r"^error: the secret file .*lab\.key already exists; a new secret would lock "
                                      r"out every machine holding the old one$",
                     hint=r"pass --force \(retriever secret new\)")
    assert key.read_text() == old
    forced = secret_new(key, "--force")
    assert forced.returncode == 0, forced.stderr
    assert key.read_text() != old and key.stat().st_mode & 0o777 == 0o600


def test_secret_new_refuses_a_folder_and_a_missing_folder(tmp_path: Path):
    assert_cli_error(secret_new(tmp_path), r"^error: cannot write the secret file .*: it is a folder$",
                     hint=r"pass a file path, e\.g\. .*deployment\.key$")
    assert_cli_error(secret_new(tmp_path / "keys" / "lab.key"),
                     r"^error: cannot write the secret file .*lab\.key: the folder .*keys does not exist$",
                     hint=r"mkdir -p .*keys$")
    assert list(tmp_path.iterdir()) == []


def test_a_deployments_status_table_shows_forged_answers_as_plain_text():
    """`retriever status` prints what a coordinator answered over the network: markup, escape
    codes and wrong types stay inert text, and nothing raises."""
    from rich.console import Console

    from retriever.cli import status_table

    answer = {"pipeline": "[bold]x[/]\x1b]0;pwned\x07", "started": True, "t_ns": 2_000_000_000, "end_ns": 10**10,
              "nodes": {"cam": {"worker": "arm\x1b[31m", "state": "running", "ticks": 60, "steps": 60, "skips": 0,
                                "errors": 0, "cpu_s": 0.5, "counts": {"late": 2}},
                        "[/]": "not a dict", "odd": {"ticks": "many", "cpu_s": "lots", "counts": [1]}}}
    console = Console(record=True, width=200, color_system=None)
    console.print(status_table(answer, "lab"))
    text = console.export_text()
    assert "30.0" in text and "25%" in text and "late 2" in text  # 60 ticks in 2 s; 0.5 s of CPU
    assert "\x1b" not in text and "[bold]x[/]" in text


def test_log_cat_briefly_as_json_and_in_a_time_range(tmp_path: Path):
    """issue 19 §3: `--brief` shows a frame as its dtype and shape, `--json` one object per line,
    `--from`/`--to` a window of tags (seconds, [from, to))."""
    from tests.log.test_foxglove import _log

    log = _log(tmp_path)  # a 10 Hz camera for 0.5 s: rgb uint8 6×8×3, depth 6×8, exposure
    brief = cli("log", "cat", str(log), "--node", "cam", "--brief", "--from", "0.1", "--to", "0.3")
    assert brief.returncode == 0, brief.stderr
    lines = brief.stdout.splitlines()
    assert [line.split("  ")[1] for line in lines] == ["cam.depth #1", "cam.exposure #1", "cam.rgb #1",
                                                       "cam.depth #2", "cam.exposure #2", "cam.rgb #2"], lines
    assert lines[2].endswith("uint8[6,8,3]") and lines[0].endswith("uint8[6,8]") and lines[1].endswith("0.02")
    as_json = cli("log", "cat", str(log), "--node", "stats", "--port", "hist", "--json", "--limit", "2")
    rows = [json.loads(line) for line in as_json.stdout.splitlines()]
    assert rows == [{"tag_ns": 0, "microstep": 2, "node": "stats", "port": "hist", "seq": 0, "value": [1, 141, 0, 0]},
                    {"tag_ns": 100_000_000, "microstep": 2, "node": "stats", "port": "hist", "seq": 1,
                     "value": [1, 0, 141, 0]}], rows
    steps = cli("log", "cat", str(log), "--steps", "--json", "--from", "0.4")
    assert [(r["node"], r["tag_ns"], r["status"]) for r in map(json.loads, steps.stdout.splitlines())] == [
        ("cam", 400_000_000, "ok"), ("stats", 400_000_000, "ok")]


def test_log_cat_summarises_big_arrays_unless_asked_for_them_whole(tmp_path: Path):
    """issue 41: every camera frame printed a 25-line numpy dump unless --brief. An array of more
    than 16 elements is one line (dtype, shape, range) by default, whole with --full."""
    from tests.log.test_foxglove import _log

    log = _log(tmp_path)  # rgb uint8 6×8×3 (k everywhere, one pixel (255, 0, 7)), depth 6×8 arange, exposure
    shown = cli("log", "cat", str(log), "--node", "cam", "--limit", "3")
    assert shown.returncode == 0, shown.stderr
    assert [line.split("  ", 2)[2] for line in shown.stdout.splitlines()] == [
        "uint8[6,8] min 0 max 47", "0.01", "uint8[6,8,3] min 0 max 255"], shown.stdout
    stats = cli("log", "cat", str(log), "--node", "stats", "--limit", "2")
    assert [line.split("  ", 2)[2] for line in stats.stdout.splitlines()] == [
        "float32[5000] min 0.0 max 0.0", "array([ 1, 141, 0, 0])"], stats.stdout
    whole = cli("log", "cat", str(log), "--node", "cam", "--port", "depth", "--limit", "1", "--full")
    assert whole.returncode == 0 and "40, 41, 42, 43, 44, 45, 46, 47]], dtype=uint8)" in whole.stdout, whole.stdout
    assert "..." not in whole.stdout and len(whole.stdout.splitlines()) == 6
    assert cli("log", "cat", str(log), "--brief", "--limit", "1").stdout.endswith("uint8[6,8]\n")
    assert_cli_error(cli("log", "cat", str(log), "--brief", "--full"),
                     r"^error: --brief and --full ask for arrays both ways$", hint="pass one of them")


def test_log_cat_shows_a_dataclass_value_read_without_its_type_by_its_fields(tmp_path: Path):
    from retriever import Rate
    from tests.log.test_foxglove import Shooter

    with Pipeline("shots") as pipe:
        Shooter().configure(name="cam") @ Rate(hz=10)
    pipe.run(duration=0.1, log=tmp_path / "run.mcap")
    shown = cli("log", "cat", str(tmp_path / "run.mcap"), "--port", "frame")
    assert shown.stdout.splitlines()[0].endswith(
        "cam.frame #0  <tests.log.test_foxglove:Shot>(camera='head', t=0.1, rgb=uint8[4,5,3] min 1 max 1, "
        "mask=uint8[4,5] min 0 max 1)"), shown.stdout
    brief = cli("log", "cat", str(tmp_path / "run.mcap"), "--port", "frame", "--brief")
    assert brief.stdout.splitlines()[0].endswith(
        "<tests.log.test_foxglove:Shot>(camera='head', t=0.1, rgb=uint8[4,5,3], mask=uint8[4,5])"), brief.stdout


def test_counters_are_said_in_words_and_spin_time_in_seconds():
    """`retriever run`'s "counted" lines and `log info`: a node whose only counter is spin_ns
    (configure(spin=)) says how long it busy-waited, not an empty list."""
    from retriever.cli import counters_in_words

    assert counters_in_words({"spin_ns": 561_234_567}) == "0.561 s busy-waiting for ticks (spin)"
    assert counters_in_words({"late": 2, "report_waits": 1, "report_wait_ns": 171_000_000, "garbage": 0}) == \
        "2 late events, 1 waits for the log (171 ms)"


UNTIL_STOPPED_SCRIPT = """
from retriever import Flow, Pipeline, Rate


class Tick(Flow):
    def __init__(self):
        self.n = 0

    def step(self):
        self.n += 1
        if self.n == 1:
            print("stepped", flush=True)
        return {"n": self.n}


with Pipeline("until_stopped") as pipe:
    Tick() @ Rate(hz=1000)
"""


def test_a_run_until_stopped_without_a_log_keeps_only_counters(tmp_path):
    """``--duration inf`` with no ``--log``: nothing will read the records, and the trace would
    grow until Ctrl-C; the run keeps counters only, says so, and its summary says the records
    were not kept (not that a log has them)."""
    import signal

    script = tmp_path / "until_stopped.py"
    script.write_text(UNTIL_STOPPED_SCRIPT, encoding="utf-8")
    proc = subprocess.Popen([str(RETRIEVER), "run", str(script), "--duration", "inf"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        assert proc.stdout.readline() == "stepped\n", proc.stderr.read()
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "--duration inf without --log: the run keeps its counters only" in err
    assert "records not kept (--keep counters)" in out and "only in the log" not in out


def test_log_cat_refuses_times_and_limits_that_are_no_numbers_of_it(tmp_path: Path):
    from tests.log.test_foxglove import _log

    log = _log(tmp_path)
    for flag, value, problem in (("--from", "nan", r"--from must be a finite number of seconds >= 0, got nan"),
                                 ("--to", "-inf", r"--to must be a finite number of seconds >= 0, got -inf"),
                                 ("--from", "1e300", r"--from must be at most 9.223e\+09 s"),
                                 ("--limit", "-1", r"--limit -1: expected a count >= 0")):
        assert_cli_error(cli("log", "cat", str(log), flag, value), "^error: " + problem)
    nothing = cli("log", "cat", str(log), "--steps", "--node", "nobody")
    assert nothing.stderr == "nothing matched; no step record in that range or of that node\n", nothing.stderr


def test_log_cat_shows_floats_with_the_digits_that_tell_them_apart():
    import numpy as np

    from retriever.log.show import show_value

    values = np.array([0.4803160625, 1 / 3])
    assert show_value(values, "summary") == "array([0.4803160625, 0.3333333333333333])"
    assert "0.4803160625" in show_value(values, "full") and "0.3333333333333333" in show_value(values, "full")


def test_the_consoles_print_no_emoji_for_a_colon_code_in_a_message():
    """Rich read ``:-1:`` in ``127.0.0.1:-1:`` (``--foxglove=-1``'s error) as the 👎 emoji."""
    from retriever.cli import console

    for printer in (console.out, console.err):
        with printer.capture() as captured:
            printer.print("cannot serve the Foxglove live view on 127.0.0.1:-1: number too small")
        assert "127.0.0.1:-1: number" in captured.get(), captured.get()
