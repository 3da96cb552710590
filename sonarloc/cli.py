"""The ``sonarloc`` command: a thin shell over the library.

Each subcommand lives in ``sonarloc/commands/<name>.py`` with ``add_arguments(parser)``
and ``run(args) -> int``; it is imported only when used. Errors on bad input become a
one-line message and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
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
        return int(args._run(args) or 0)
    except (SonarlocError, ValueError, OSError) as err:
        print(f"sonarloc {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
