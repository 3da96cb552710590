"""The `sonarloc` shell itself: behaviour common to every command."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from sonarloc.cli import stdout_reader_gone

MAPS = Path(__file__).resolve().parents[2] / "maps"


def test_a_reader_that_stops_early_is_not_an_error(tmp_path: Path, run_cli, cli_command):
    # `sonarloc fit SCAN --jsonl | head`: the reader closes the pipe; the command stops
    # quietly with 128 + SIGPIPE, as shell tools do, instead of "error: Broken pipe"
    # (or Python's "Exception ignored ... BrokenPipeError" when it was the last flush).
    scan = tmp_path / "scan.csv"
    run_cli("simulate", "--map", str(MAPS / "paper_fig5.geojson"), "--rig", "pan",
            "--at", "0,0,0", "--out", str(tmp_path / "log.jsonl"), "--scan-csv", str(scan),
            check=True)
    for output in ("--json", "--jsonl"):
        cmd, env = cli_command("fit", str(scan), output)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
        assert proc.stdout is not None and proc.stderr is not None
        proc.stdout.close()  # gone before the first byte, as `| head -0` would be
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=120) == 141 and err == "", (output, proc.returncode, err)


def test_only_a_closed_stdout_counts_as_the_reader_gone(monkeypatch, tmp_path: Path):
    # A broken pipe from a device's socket stays an error: the quiet exit needs stdout
    # itself to be a pipe without a reader.
    read_end, write_end = os.pipe()
    with open(write_end, "w") as out:
        monkeypatch.setattr(sys, "stdout", out)
        assert not stdout_reader_gone()
        os.close(read_end)
        assert stdout_reader_gone()
    with open(tmp_path / "out.txt", "w") as out:
        monkeypatch.setattr(sys, "stdout", out)
        assert not stdout_reader_gone()


def test_every_command_and_option_help_says_what_it_is():
    # `sonarloc plot scan --help` printed only usage and options: each (sub)command's
    # --help starts with a description, as `sonarloc fit --help` does.
    from sonarloc.cli import build_parser

    def parsers(parser: argparse.ArgumentParser, name: str):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    yield f"{name} {sub_name}", sub
                    yield from parsers(sub, f"{name} {sub_name}")

    found = dict(parsers(build_parser(), "sonarloc"))
    assert {"sonarloc fit", "sonarloc plot scan", "sonarloc rosbag export"} <= set(found)
    missing = [name for name, p in found.items() if not (p.description or "").strip()]
    assert not missing, missing
    # and every option says what it is (serve-sim's --rig/--tier/--seed, rosbag export's
    # --pose-topic/--map-frame/--odom-frame and plot's --dpi showed a bare metavar)
    bare = [(name, a.option_strings) for name, p in found.items() for a in p._actions
            if a.option_strings and not a.help]
    assert not bare, bare


def test_fit_bad_option_values_are_reported_like_any_bad_input(tmp_path: Path, run_cli):
    # One line "sonarloc fit: error: --OPTION ...", exit 2 (some lacked "error:", and
    # --speed-of-sound named the library's `c_mps` only).
    scan = tmp_path / "scan.csv"
    scan.write_text("t_s,x_m,y_m,yaw_deg,tof_us\n0,0,0,0,8000\n")
    for option, value in (("--speed-of-sound", "-3"), ("--temperature", "-500"),
                          ("--odometry-sd", "-1"), ("--max-travel", "-1"),
                          ("--block-rows", "0")):
        proc = run_cli("fit", str(scan), option, value)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, (option, proc.stderr)
        assert lines[0].startswith(f"sonarloc fit: error: {option}"), (option, proc.stderr)


def _overwrite_cases(tmp: Path) -> list[tuple[list[str], str]]:
    """(argv, the message) of each command naming one file as an input and an output, or
    as two outputs."""
    log, poses, scan, rig = (tmp / n for n in ("log.jsonl", "poses.csv", "scan.csv", "rig.json"))
    geo = tmp / "room.geojson"
    return [
        (["localize", str(log), "--map", str(geo), "--out", str(log)],
         f"--out {log} is the input LOG"),
        (["localize", str(log), "--map", str(geo), "--out", str(tmp / "." / "room.geojson")],
         "is the input --map"),
        (["map", "build", str(log), "--poses", str(poses), "--out", str(poses)],
         "is the input --poses"),
        (["simulate", "--map", str(geo), "--out", str(geo)], "is the input --map"),
        (["simulate", "--map", str(geo), "--rig", str(rig), "--out", str(tmp / "new.jsonl"),
          "--scan-csv", str(rig)], "--scan-csv"),
        (["simulate", "--map", str(geo), "--out", str(scan), "--scan-csv", str(scan)],
         f"--scan-csv {scan} is also --out"),
        (["record", str(log), "--out", str(log)], "is the input SOURCE"),
        (["rosbag", "export", str(poses), "--log", str(log), "--out", str(log)],
         "is the input --log"),
        (["serve-sim", "--log", str(log), "--candump", str(log)], "is the input --log"),
        (["plot", "trajectory", str(log), "--poses", str(poses), "--out", str(poses)],
         "is the input --poses"),
        (["plot", "scan", str(scan), "--out", str(scan)], "is the input SCAN"),
        (["drive", "--poses", str(tmp / "p.csv"), "--plot", str(tmp / "p.csv")],
         "is also --poses"),
    ]


def test_no_command_writes_over_a_file_it_reads(tmp_path: Path, capsys):
    # `sonarloc localize LOG --out LOG` opened the recording for writing before reading
    # it: 1740 lines became one, and the command then said the log had no record
    from sonarloc.cli import main

    contents = {}
    for name in ("log.jsonl", "poses.csv", "scan.csv", "rig.json"):
        (tmp_path / name).write_text(f"{name}: must survive\n", encoding="utf-8")
        contents[name] = f"{name}: must survive\n"
    geo = (MAPS / "room.geojson").read_text(encoding="utf-8")
    (tmp_path / "room.geojson").write_text(geo, encoding="utf-8")
    contents["room.geojson"] = geo
    for argv, message in _overwrite_cases(tmp_path):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "overwrit" in err and len(err.splitlines()) == 1, (argv, err)
        for name, text in contents.items():
            assert (tmp_path / name).read_text(encoding="utf-8") == text, (argv, name)
        assert not (tmp_path / "p.csv").exists() and not (tmp_path / "new.jsonl").exists()


def test_localize_out_naming_its_log_keeps_the_recording(tmp_path: Path, run_cli):
    # the same through a real process and a real log: refused before anything is opened
    log = tmp_path / "drive.jsonl"
    run_cli("simulate", "--map", str(MAPS / "room.geojson"), "--out", str(log),
            "--duration", "2", check=True)
    before = log.read_bytes()
    proc = run_cli("localize", str(log), "--map", str(MAPS / "room.geojson"),
                   "--out", str(log))
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip() == (f"sonarloc localize: error: --out {log} is the input LOG: "
                                   "it would be overwritten")
    assert log.read_bytes() == before and len(before.splitlines()) > 100
