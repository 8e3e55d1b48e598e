"""``fednav-view FILE.rrd``: open a fednav recording in the Rerun viewer.

The recording embeds its blueprint (written by the service), so by default this runs the installed
``rerun`` CLI (rerun-sdk 0.41, next to this Python) on the file: ``rerun FILE.rrd``.

Options:

* ``--blueprint-from-file`` (default): use the blueprint embedded in the recording;
* ``--rebuild-blueprint``: rebuild the blueprint from the entities found in the recording (vehicles,
  pipelines and their families guessed from what was logged) and open it with the file, e.g. for
  recordings written without one;
* ``--web``: serve the web viewer instead of opening a native window (works without a display;
  open the printed URL in a browser);
* ``--print-command``: print the command instead of running it.

Without a display (Linux with neither DISPLAY nor WAYLAND_DISPLAY) the native viewer cannot start:
the command prints what to run instead and exits with code 3. Exit code 2: file missing or not a
recording.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

EXIT_BAD_FILE = 2
EXIT_NO_VIEWER = 3


def rerun_executable() -> str | None:
    """The ``rerun`` CLI of this environment (next to ``sys.executable``), else the one on PATH."""
    here = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    if here.is_file():
        return str(here)
    return shutil.which("rerun")


def has_display() -> bool:
    """Whether a native window can open (Linux/BSD: an X11 or Wayland display is set)."""
    if sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def guess_families(vehicle: str, pipelines: list[str], entity_paths: list[str]) -> dict[str, str]:
    """Pipeline -> family, guessed from the entities a recording holds (for ``--rebuild-blueprint``)."""
    from fednav.service.transport import rerun_paths as paths

    out = {}
    for p in pipelines:
        root = paths.pipeline_root(vehicle, p) + "/"
        subtrees = {e[len(root) :].split("/", 1)[0] for e in entity_paths if e.startswith(root)}
        if "integrity" in subtrees:
            out[p] = "integrity"
        elif "sharing" in subtrees:
            out[p] = "federated"
        elif "imm" in subtrees:
            out[p] = "imm"
        elif "alignment" in subtrees:
            out[p] = "transfer_alignment"
        elif "underwater" in subtrees:
            out[p] = "underwater"
        else:
            out[p] = "loosely_coupled"
    return out


def rebuild_blueprint(file: Path, out: Path) -> Mapping[str, Mapping[str, str]]:
    """Write a blueprint (.rbl) rebuilt from the recording's entities; returns vehicle -> families."""
    from fednav.dashboards.blueprints import build_fleet_blueprint
    from fednav.dashboards.inspect import read_series, summarize

    info, data = read_series(file)
    summary = summarize(info, data, str(file))
    vehicles = summary["vehicles"]
    families: dict[str, dict[str, str]] = {}
    merged: dict[str, str] = {}
    for v in vehicles:
        pipes = sorted({pp.source for e in data if (pp := _parse(e)) and pp.vehicle == v and pp.is_pipeline})
        families[v] = guess_families(v, pipes, list(data))
        merged.update(families[v])
    build_fleet_blueprint(vehicles, merged).save(summary["application_id"], out)
    return families


def _parse(entity: str):
    from fednav.service.transport import rerun_paths as paths

    return paths.parse(entity)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="fednav-view", description="Open a fednav recording in the Rerun viewer"
    )
    ap.add_argument("file", type=Path, help="recording (.rrd)")
    bp = ap.add_mutually_exclusive_group()
    bp.add_argument(
        "--blueprint-from-file",
        action="store_true",
        help="use the blueprint embedded in the recording (default)",
    )
    bp.add_argument(
        "--rebuild-blueprint", action="store_true", help="rebuild the blueprint from the recorded entities"
    )
    ap.add_argument("--web", action="store_true", help="serve the web viewer (no display needed)")
    ap.add_argument("--print-command", action="store_true", help="print the viewer command and exit")
    args = ap.parse_args(argv)

    file: Path = args.file
    if not file.is_file():
        print(f"fednav-view: error: {file}: no such file", file=sys.stderr)
        return EXIT_BAD_FILE
    try:
        from rerun.chunk import RrdReader

        if not RrdReader(file).recordings():
            raise ValueError("the file holds no recording")
    except Exception as exc:
        print(f"fednav-view: error: {file}: not a readable Rerun recording ({exc})", file=sys.stderr)
        return EXIT_BAD_FILE

    exe = rerun_executable()
    if exe is None:
        print(
            "fednav-view: error: the 'rerun' command (rerun-sdk 0.41) is not installed in this "
            "environment; install the project (make test / pip install -e .)",
            file=sys.stderr,
        )
        return EXIT_NO_VIEWER

    with tempfile.TemporaryDirectory(prefix="fednav-view-") as tmp:
        extra: list[str] = []
        if args.rebuild_blueprint:
            rbl = Path(tmp) / "fednav.rbl"
            try:
                families = rebuild_blueprint(file, rbl)
            except Exception as exc:
                print(f"fednav-view: error: could not rebuild the blueprint: {exc}", file=sys.stderr)
                return EXIT_BAD_FILE
            print(f"fednav-view: rebuilt blueprint for {dict(families)}", file=sys.stderr)
            extra.append(str(rbl))
        cmd = [exe, *(["--serve-web"] if args.web else []), str(file), *extra]
        if args.print_command:
            print(shlex.join(cmd))
            return 0
        if not args.web and not has_display():
            print(
                "fednav-view: error: no display (DISPLAY / WAYLAND_DISPLAY unset), the native viewer "
                "cannot open a window.\n"
                f"  on a machine with a display run:   {shlex.join([Path(exe).name, str(file)])}\n"
                f"  or serve the web viewer from here: fednav-view --web {shlex.quote(str(file))}\n"
                f"  or print a text summary:           fednav-inspect {shlex.quote(str(file))}",
                file=sys.stderr,
            )
            return EXIT_NO_VIEWER
        try:
            rc = subprocess.run(cmd, check=False).returncode
        except OSError as exc:
            print(f"fednav-view: error: could not start {shlex.join(cmd)}: {exc}", file=sys.stderr)
            return EXIT_NO_VIEWER
        except KeyboardInterrupt:
            return 130
        if rc != 0:
            print(
                f"fednav-view: the viewer exited with code {rc} ({shlex.join(cmd)}); without a GPU or "
                "display try --web, or fednav-inspect for a text summary",
                file=sys.stderr,
            )
        return rc


if __name__ == "__main__":
    raise SystemExit(main())
