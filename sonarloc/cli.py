"""The ``sonarloc`` command: a thin shell over the library.

Each subcommand lives in ``sonarloc/commands/<name>.py`` with ``add_arguments(parser)``
and ``run(args) -> int``; it is imported only when used. Errors on bad input become a
one-line message and exit status 2; a reader of stdout that stops early (``| head``) ends
the command quietly with 141 (128 + SIGPIPE), as it does a shell tool.
"""

from __future__ import annotations

import argparse
import importlib
import io
import os
import select
import signal
import sys
from collections.abc import Sequence

from sonarloc import __version__
from sonarloc.errors import SonarlocError

# name -> (module, one-line help). Keep in the order of FORMATS.md section 6.
COMMANDS: dict[str, tuple[str, str]] = {
    "drive": ("sonarloc.commands.drive", "the main job: simulated drive, fit, EKF, report, plot"),
    "fit": ("sonarloc.commands.fit", "landmarks from TOF readings of a scan CSV"),
    "simulate": ("sonarloc.commands.simulate", "simulated log (and scan CSV) from a map"),
    "localize": ("sonarloc.commands.localize", "EKF localization of a log against a map"),
    "map": ("sonarloc.commands.map", "landmark maps from logs (map build)"),
    "serve-sim": ("sonarloc.commands.serve_sim", "a simulated sonar module speaking the protocol"),
    "record": ("sonarloc.commands.record", "readings from a device, bus or file into a log"),
    "plot": ("sonarloc.commands.plot", "plot a scan with model curves, a sonar map, a trajectory"),
    "bench": ("sonarloc.commands.bench", "run the benchmarks, gather speed-against-error tables"),
    "rosbag": ("sonarloc.commands.rosbag", "ROS bags: import Range/Odometry, export poses"),
}


BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """One BLAS thread unless the user chose otherwise (before numpy loads BLAS, which
    reads the setting: the CLI imports no numpy before a command's module).

    The fitter's and the EKF's linear algebra is batched 3x3 to 6x6 systems, where threads
    cannot help and OpenBLAS's idle ones spin between the many small calls: `sonarloc fit`
    on bench_fit section 4's scan 2.66 -> 2.29 s CPU, the landmarks the same
    (docs/FITTING.md); `sonarloc drive` the same output, its CPU time within the noise
    (medians of 3 on the shared 2 cores: 20.6 s with one thread, 19.3 s with two)."""
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")


def stdout_reader_gone() -> bool:
    """Whether stdout is a pipe whose reader has closed it (``sonarloc localize LOG | head``).

    Tells that broken pipe from one of a device's sockets, which is a real error. Where
    ``poll`` is missing (Windows), a broken pipe is taken to be stdout's."""
    if not hasattr(select, "poll"):
        return True
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, io.UnsupportedOperation):
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def quit_on_closed_stdout() -> int:
    """Exit status after stdout's reader went away: 128 + SIGPIPE, silently, as a shell
    tool does. Later writes, and the interpreter's last flush, go to /dev/null instead of
    failing again with "Exception ignored ... BrokenPipeError"."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return 128 + int(getattr(signal, "SIGPIPE", 13))


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser; with ``only``, just that subcommand's module is imported."""
    parser = argparse.ArgumentParser(
        prog="sonarloc",
        description="Localize a mobile robot with time-of-flight sonar (Kuc's forward model).",
    )
    parser.add_argument("--version", action="version", version=f"sonarloc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=help_text)
            continue
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=(module.__doc__ or help_text).strip(),
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    one_blas_thread()
    args_list = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in args_list if not a.startswith("-")), None)
    parser = build_parser(only=first if first in COMMANDS else "")
    args = parser.parse_args(args_list)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        status = int(args._run(args) or 0)
        sys.stdout.flush()  # here, so that a reader that went away is seen below
        return status
    except (SonarlocError, ValueError, OSError) as err:
        if isinstance(err, BrokenPipeError) and stdout_reader_gone():
            return quit_on_closed_stdout()
        print(f"sonarloc {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
