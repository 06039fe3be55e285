"""Options several commands share (--keep, --foxglove, --rerun, TLS, --secret, --insecure), each written
once so that every command says it alike."""

from __future__ import annotations

import typer

from ..errors import BackendError
from ..log.rerun import RERUN_VIEWER_URL
from .console import fail

#: `--foxglove` without a port: the Foxglove app's default for a WebSocket connection
FOXGLOVE_PORT = 8765
FOXGLOVE_OPTION = typer.Option(
    "--foxglove", metavar="[PORT]",
    help=f"zenoh: stream the run live to the Foxglove app (its WebSocket server in this process, on "
         f"127.0.0.1:PORT, default {FOXGLOVE_PORT}; needs pip install 'retriever-robotics\\[foxglove]').")

#: `--rerun` without a target: the viewer that `rerun` starts on this machine
RERUN_URL = RERUN_VIEWER_URL
RERUN_OPTION = typer.Option(
    "--rerun", metavar="[TARGET]",
    help=f"zenoh: stream the run live to Rerun: TARGET a running viewer's gRPC URL (default {RERUN_URL}, "
         "the viewer `rerun` starts) or a PATH.rrd the stream is saved to as it goes (needs pip install "
         "'retriever-robotics\\[rerun]').")

KEEP_OPTION = typer.Option(
    metavar="trace|records|counters",
    help="What the run keeps in memory: 'trace' every event's value (the default of run without --log or on "
         "inproc); 'records' the events' ids and tags and the step records, the values only in --log (on zenoh "
         "they then reach this process only to be logged; the default of deploy without --log); 'counters' "
         "nothing but the counters, each record freed once --log has it: memory stays bounded however long "
         "the run (the default of a logged run on zenoh and of a logged deploy).")


TLS_CA_OPTION = typer.Option("--tls-ca", metavar="FILE", help="TLS: the CA certificate (PEM) that signs every "
                             "certificate of the deployment; with --tls-cert and --tls-key every link is mutual "
                             "TLS (endpoints tls/HOST:PORT).")
TLS_CERT_OPTION = typer.Option("--tls-cert", metavar="FILE", help="TLS: this machine's certificate (PEM), naming "
                               "the addresses it is reached at.")
TLS_KEY_OPTION = typer.Option("--tls-key", metavar="FILE", help="TLS: this machine's private key (PEM).")


def tls_files(ca, cert, key):
    """--tls-ca, --tls-cert, --tls-key as the zenoh backend takes them (None: no TLS)."""
    from ..backends.zenoh.access import TlsFiles

    try:
        return TlsFiles.of(ca, cert, key)
    except Exception as exc:
        fail(exc)


def check_keep(keep: str | None) -> None:
    """--keep names one of the trace's keep modes, or the command fails saying which there are."""
    from ..trace import KEEP

    if keep is not None and keep not in KEEP:
        fail(BackendError(f"--keep {keep!r} is none of 'trace', 'records', 'counters'\n    hint: --keep records keeps "
                          "the events' ids and the step records (the values only in --log); --keep trace every "
                          "value; --keep counters nothing but the counters (the records only in --log)"))


#: --secret and --insecure of the commands that join a deployment's namespace
SECRET_HELP = "A deployment secret file (>= 16 bytes, mode 600): only holders of it may join."
INSECURE_HELP = "Join without a secret: anyone who reaches the endpoints may. Only for a lab on a trusted network."
