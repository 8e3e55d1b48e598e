"""``make screenshots``: each recording family in Rerun's web viewer, every blueprint tab captured
in headless Chromium (Playwright driving the SYSTEM chromium; it never downloads a browser).

Steps per family (``FAMILIES``: scenario, seconds of it to record):

1. record the scenario in-process (``dashboards.record``), compacted;
2. check every panel of the embedded blueprint against the recording (:func:`empty_panels`: a
   view whose entity filter matches no recorded entity is reported; the recordings are read
   with Rerun's reader);
3. serve the file with ``rerun --serve-web`` (web viewer + gRPC proxy on free local ports), open it
   in Chromium, wait until the page stops changing (the viewer finished loading), then for each
   top-level tab send the same blueprint with that tab active and the side panels collapsed
   (``RecordingStream.send_blueprint`` to the proxy) and save ``<out>/<family>-<tab>.png``.

Install (Debian/Ubuntu, as root): ``apt-get install -y chromium``; the Python side comes with
``make`` (the ``screenshots`` extra pins Playwright). ``--chromium PATH`` or ``$CHROMIUM`` picks
another executable. Software rendering (SwiftShader) is slow: loading a recording takes tens of
seconds on a busy 2-core machine, hence the short recordings.

    .venv/bin/python -m fednav.dashboards.screenshots --out docs/images            # every family
    .venv/bin/python -m fednav.dashboards.screenshots --only demo --tabs Overview  # one family, one tab
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

#: family -> (scenario, seconds recorded). Seed 002 / 003 / 004 are the families of issues 8-10.
FAMILIES: dict[str, tuple[str, float]] = {
    "demo": ("demo_product", 120.0),
    "seed000": ("seed000_faults", 330.0),
    "seed001": ("seed001_ramp", 180.0),
    "seed002": ("seed002_wing", 60.0),
    "seed003": ("seed003_outliers", 120.0),
    "seed004": ("seed004_usbl_fault", 620.0),  # the USBL fault starts at 500 s
}


def find_chromium(explicit: str | None = None) -> str | None:
    """The system Chromium / Chrome executable, or None."""
    for c in (explicit, os.environ.get("CHROMIUM")):
        if c and Path(c).is_file():
            return c
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


# --- panels vs data -------------------------------------------------------------------------------
@dataclass
class Panel:
    tab: str
    name: str
    filters: list[str]


def _views(node, tab: str) -> Iterable[Panel]:
    contents = getattr(node, "contents", None)
    if _is_view(node):
        origin = str(node.origin)
        raw = contents if isinstance(contents, list | tuple) else [contents]
        filters = [str(c).replace("$origin", origin.rstrip("/")) for c in raw if c is not None]
        yield Panel(tab, str(node.name), filters)
        return
    for child in contents or []:
        yield from _views(child, tab)


def _is_view(node) -> bool:
    return type(node).__name__.endswith("View")


def tabs_of(blueprint) -> list[tuple[str, object]]:
    """(name, container) of each top-level tab of a one-vehicle blueprint."""
    root = blueprint.root_container
    return [(str(t.name), t) for t in root.contents]


def _match(flt: str, entity: str) -> bool:
    flt = flt.strip()
    if flt.startswith("-"):
        return False
    flt = flt.lstrip("+ ").rstrip("/")
    if flt.endswith("/**"):
        base = flt[:-3]
        return entity == base or entity.startswith(base + "/")
    return entity == flt


def empty_panels(blueprint, entities: Iterable[str]) -> list[Panel]:
    """Views of ``blueprint`` whose entity filters match none of ``entities`` (no data shown)."""
    ents = [e for e in entities if not e.startswith("/__")]
    out = []
    for tab, node in tabs_of(blueprint):
        for panel in _views(node, tab):
            if not any(_match(f, e) for f in panel.filters for e in ents):
                out.append(panel)
    return out


def recorded_entities(rrd: Path) -> set[str]:
    from rerun.chunk import RrdReader

    r = RrdReader(rrd)
    return {ch.entity_path for ch in r.stream(store=r.recordings()[0])}


# --- reading a screenshot back --------------------------------------------------------------------
def png_rgb(path: Path):
    """Decode an 8-bit RGB / RGBA non-interlaced PNG (what Chromium writes) to an (h, w, 3) array."""
    import struct
    import zlib

    import numpy as np

    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG")
    pos, idat, hdr = 8, b"", None
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    w, h, depth, ctype, _, _, interlace = hdr
    if depth != 8 or ctype not in (2, 6) or interlace:
        raise ValueError(f"{path}: unsupported PNG (depth {depth}, colour type {ctype})")
    bpp = 3 if ctype == 2 else 4
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(h, 1 + w * bpp)
    out = np.zeros((h, w * bpp), dtype=np.int32)
    prev = np.zeros(w * bpp, dtype=np.int32)
    for y in range(h):
        f, line = raw[y, 0], raw[y, 1:].astype(np.int32)
        if f == 0:
            cur = line
        elif f == 2:
            cur = (line + prev) & 0xFF
        else:  # 1 (sub), 3 (average), 4 (Paeth) depend on the left pixel: byte loop
            cur = np.zeros_like(line)
            for x in range(line.size):
                a = cur[x - bpp] if x >= bpp else 0
                b = prev[x]
                c = prev[x - bpp] if x >= bpp else 0
                if f == 1:
                    pred = a
                elif f == 3:
                    pred = (a + b) // 2
                else:
                    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                cur[x] = (line[x] + pred) & 0xFF
        out[y], prev = cur, cur
    return out.reshape(h, w, bpp)[:, :, :3].astype(np.uint8)


#: Below this fraction of coloured pixels a screenshot shows no data (``main``, the test).
BLANK_FRACTION = 0.005


def coloured_fraction(path: Path) -> float:
    """Share of pixels with a saturated colour (plot lines, state lanes, markers): a viewer with
    no data shown is grey and white."""
    img = png_rgb(path).astype(int)
    sat = img.max(axis=2) - img.min(axis=2)
    return float((sat > 60).mean())


# --- capture --------------------------------------------------------------------------------------
def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _slug(s: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", s.lower()).strip("-")


def _wait_stable(page, timeout_s: float, period_s: float = 4.0) -> bool:
    """Wait until two screenshots ``period_s`` apart are identical (the viewer finished loading)."""
    deadline = time.monotonic() + timeout_s
    prev = None
    while time.monotonic() < deadline:
        time.sleep(period_s)
        cur = page.screenshot()
        if prev is not None and cur == prev:
            return True
        prev = cur
    return False


def capture(
    rrd: Path,
    blueprint_for_tab,
    tab_names: list[str],
    out_dir: Path,
    prefix: str,
    chromium: str,
    load_timeout_s: float = 240.0,
    size: tuple[int, int] = (1400, 860),
) -> list[Path]:
    """Serve ``rrd``, open it in headless Chromium and save one PNG per tab."""
    import rerun as rr
    from playwright.sync_api import sync_playwright
    from rerun.chunk import RrdReader

    store = RrdReader(rrd).recordings()[0]
    web, grpc = _free_port(), _free_port()
    exe = Path(sys.executable).parent / "rerun"
    server = subprocess.Popen(
        [str(exe), "--serve-web", "--web-viewer-port", str(web), "--port", str(grpc), str(rrd)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "RERUN_ANALYTICS_ENABLED": "false"},
        # the `rerun` script runs the viewer binary as its child: a group of its own, so that stopping
        # it stops the server too (terminating the script alone left the binary serving, at full CPU)
        start_new_session=True,
    )
    saved: list[Path] = []
    try:
        time.sleep(2.0)
        proxy = f"rerun+http://127.0.0.1:{grpc}/proxy"
        url = f"http://127.0.0.1:{web}/?url=" + proxy.replace(":", "%3A").replace("/", "%2F").replace(
            "+", "%2B"
        )
        rec = rr.RecordingStream(store.application_id, recording_id=store.recording_id)
        rec.connect_grpc(proxy)
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=chromium,
                headless=True,
                args=["--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"],
            )
            page = browser.new_page(viewport={"width": size[0], "height": size[1]})
            page.goto(url)
            rec.send_blueprint(blueprint_for_tab(0), make_active=True, make_default=False)
            _wait_stable(page, load_timeout_s)
            last = page.screenshot()
            for i, name in enumerate(tab_names):
                rec.send_blueprint(blueprint_for_tab(i), make_active=True, make_default=False)
                rec.flush(timeout_sec=5.0)
                deadline = time.monotonic() + 60.0  # first wait for the new tab to show...
                while i > 0 and page.screenshot() == last and time.monotonic() < deadline:
                    time.sleep(1.0)
                _wait_stable(page, 60.0, period_s=3.0)  # ...then for it to finish drawing
                path = out_dir / f"{prefix}-{_slug(name)}.png"
                last = page.screenshot(path=str(path))
                saved.append(path)
            browser.close()
        rec.disconnect()
    finally:
        _stop_group(server)
    return saved


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM the process group of ``proc`` (started with ``start_new_session``), SIGKILL after 10 s."""
    for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            continue
        try:  # the script is gone: make sure its children are too
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        return


def screenshot_family(
    family: str,
    out_dir: Path,
    chromium: str | None,
    only_tabs: list[str] | None = None,
    work: Path | None = None,
    duration_s: float | None = None,
) -> dict:
    """Record, check and (with a browser) capture one family. Returns a report dict."""
    import rerun.blueprint as rrb

    from fednav.dashboards.blueprints import vehicle_tabs
    from fednav.dashboards.record import record
    from fednav.service.config import recording_kinds
    from fednav.service.transport import rerun_paths as paths
    from fednav.simulators.evaluate import service_config
    from fednav.simulators.scenario import load_scenario

    scenario, default_s = FAMILIES[family]
    sc = load_scenario(scenario)
    cfg = service_config(sc)
    work = work or Path(tempfile.mkdtemp(prefix="fednav-shots-"))
    rrd = work / f"{family}.rrd"
    record(sc, rrd, cfg=cfg, optimize=True, duration_s=duration_s or default_s)
    pipelines = recording_kinds(cfg.pipelines)

    def bp(active: int) -> rrb.Blueprint:
        tabs = vehicle_tabs("v1", pipelines)
        tabs.active_tab = active
        return rrb.Blueprint(
            rrb.Tabs(*tabs.contents, active_tab=active, name="v1"),
            rrb.TimePanel(timeline=paths.MISSION_TIMELINE, state="collapsed"),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            auto_views=False,
            auto_layout=False,
        )

    full = bp(0)
    empty = empty_panels(full, recorded_entities(rrd))
    names = [n for n, _ in tabs_of(full)]
    wanted = [i for i, n in enumerate(names) if not only_tabs or n in only_tabs]
    report = {
        "family": family,
        "rrd": str(rrd),
        "tabs": names,
        "empty_panels": [(e.tab, e.name) for e in empty],
    }
    if chromium is None:
        report["screenshots"] = []
        return report
    out_dir.mkdir(parents=True, exist_ok=True)
    report["screenshots"] = [
        str(p)
        for p in capture(rrd, lambda i: bp(wanted[i]), [names[i] for i in wanted], out_dir, family, chromium)
    ]
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="fednav-screenshots", description=__doc__.split("\n\n")[0].replace("``", "")
    )
    ap.add_argument("--out", type=Path, default=Path("docs/images"))
    ap.add_argument("--only", action="append", choices=list(FAMILIES), help="families (default: all)")
    ap.add_argument("--tabs", action="append", help="tab names to capture (default: all)")
    ap.add_argument("--duration", type=float, help="seconds of each scenario to record")
    ap.add_argument("--chromium", help="browser executable (default: $CHROMIUM or chromium on PATH)")
    ap.add_argument("--check-only", action="store_true", help="record and check panels, no browser")
    args = ap.parse_args(argv)
    chromium = None if args.check_only else find_chromium(args.chromium)
    if chromium is None and not args.check_only:
        print("no chromium found: apt-get install -y chromium (or --chromium PATH)", file=sys.stderr)
        return 2
    bad = 0
    for fam in args.only or list(FAMILIES):
        r = screenshot_family(fam, args.out, chromium, args.tabs, duration_s=args.duration)
        print(f"{fam}: tabs {r['tabs']}")
        for tab, name in r["empty_panels"]:
            print(f"  EMPTY panel: {tab} / {name}")
        for p in r["screenshots"]:
            # the viewer's welcome page (a recording or blueprint it could not load) and an
            # unrendered tab are grey and white: 0.35 % coloured pixels; drawn tabs 1-5 %
            blank = coloured_fraction(Path(p)) < BLANK_FRACTION
            print(f"  {p}" + ("  BLANK: the viewer shows no data (did the recording load?)" if blank else ""))
            bad += blank
        bad += len(r["empty_panels"])
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
