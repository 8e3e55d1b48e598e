"""``fednav-replay MAPPING --suggest-config [OUT.toml]``: a service configuration that fits the log.

What the filter has to assume about a user's sensors, estimated from their own log and written
with where every number came from:

1. **IMU noise** (angle and velocity random walk). On a still part of the log (20 s or more at
   rest, the fixes' speed below 0.3 m/s where there are fixes): the overlapping Allan deviation of
   each gyro and accelerometer axis, its white-noise level at tau = 1 s (IEEE Std 952-1997, annex C:
   sigma(tau) = N / sqrt(tau)) and its floor (bias instability B = min sigma / 0.664). Without a
   still part: the sample-to-sample scatter in motion (robust second differences of the rates:
   for white noise of density N at interval dt, std(x_k+1 - 2 x_k + x_k-1) = sqrt(6) N / sqrt(dt);
   a car's smooth motion hardly enters at 100 Hz, its vibration does, which errs on the safe side).
2. **IMU bias level**. On a still part: the gyro's rate about the vertical minus the Earth's
   (Omega sin(latitude)) and the accelerometer's |f| minus normal gravity. In motion it cannot be
   read off the data; a short in-process run of the service's own engine (the same
   ``VehicleLoop`` as the service, on the first ``RUN_S`` seconds of the log) tells whether the
   grade's bias model holds: its normalised innovations (NIS per degree of freedom, 1 when the
   filter's model is right, far above 1 when it trusts the IMU too much).
3. **The grade**: the best preset (service/ins/imu_grades.py: navigation, tactical,
   industrial_mems, consumer_mems) whose numbers cover the measured noise (within 25 %) and, on a
   still part, whose bias sigmas cover the measured biases (within 3 sigma); then the in-process
   run, one grade lower at a time while the NIS per degree of freedom is above ``NIS_LIMIT``. Worse
   than consumer_mems: consumer_mems with the measured numbers written explicitly.
4. **Fixes**. The sigmas the fixes carry (the checks' summary: GST, covariance, receiver accuracy
   or GnssFix's defaults); their white part from the fix-to-fix scatter against the solution's
   own displacement (the in-process run's velocity integrated between two fixes: the receiver's
   slowly varying error cancels over 0.1 s, its white noise does not); the correlated part
   sqrt(sigma_fix^2 - white^2), at least ``MIN_CORRELATED_FRACTION`` of the sigma, becomes
   ``gnss_correlated_error`` (docs/own_data.md: a fix's sigma is its total error). The correlation
   time needs a long static log to measure: 30 s, the value measured on real receiver fixes
   (docs/own_data.md, 31-42 s), unless told otherwise.

The antenna lever arm is not estimated (measure it); the written file says so.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fednav.service import earth
from fednav.service.ins.imu_grades import GRADES, PRESETS

from .checks import REST_ACCEL_STD_MPS2, REST_RATE_RPS, FixData, ImuData, Report
from .mapping import ReplayMapping
from .sources import all_events

STILL_MIN_S = 20.0  # a still part this long gives the Allan deviation at tau = 1 s with ~5 % error
STILL_SPEED_MPS = 0.3
NOISE_MARGIN = 1.25  # a grade covers a measured noise density up to this factor above its own
BIAS_MARGIN = 3.0  # ... and a measured bias up to this many of its sigmas
NIS_LIMIT = 2.0  # NIS per degree of freedom above this: the grade's model trusts the IMU too much
#: ... or above this x the most cautious grade's (whose innovations reflect only the fix model)
NIS_RELATIVE = 1.5
RUN_S = 120.0  # the in-process run uses the log's first RUN_S seconds
SETTLE_S = 10.0  # innovations of the first seconds after the start are not used
DEFAULT_TAU_S = 30.0
WHITE_ONLY_RATIO = 1.3  # fix sigma below 1 / this x its white scatter: the filter would trust them too much
#: the correlated part is modelled on every axis, at least this fraction of the fixes' sigma. Real
#: receivers' errors are correlated over tens of seconds, and at 10 Hz even a correlated part well
#: below the white one dominates once the white part averages out. Until 2026-12-01 it was modelled
#: only when the sigma exceeded the white scatter 1.3x on every axis: a drive with 0.5 m white + 0.3 m
#: correlated error (sigma / white scatter measured 1.15-1.26, and 1.09-1.35 on a shorter log: the
#: scatter of 600-900 fixes is measured to ~10 %) was fused as independent, horizontal error 0.38 m
#: against a 1-sigma of 0.076 m (5x overconfident); with the states 0.23 m against 0.37 m. A white
#: receiver gets a correlated state of 30 % of its sigma: its reported sigma a little larger than
#: needed, the cautious side.
MIN_CORRELATED_FRACTION = 0.3
DPSH_PER_RPSS = 180.0 / math.pi * 60.0  # rad/sqrt(s) -> deg/sqrt(h)
ORDER = tuple(GRADES)  # best first: navigation, tactical, industrial_mems, consumer_mems


class SuggestError(ValueError):
    pass


@dataclass
class Suggestion:
    grade: str
    imu_overrides: dict[str, float]
    noise: dict
    bias: dict | None
    runs: list[dict]
    fixes: dict
    correlated: dict | None
    toml: str = ""
    notes: list[str] = field(default_factory=list)
    #: per override, what was done (the comment of its line in the written file)
    imu_override_why: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "grade": self.grade,
            "imu_overrides": self.imu_overrides,
            "noise": self.noise,
            "bias": self.bias,
            "runs": self.runs,
            "fixes": self.fixes,
            "gnss_correlated_error": self.correlated,
            "notes": self.notes,
        }

    def summary_text(self) -> str:
        n = self.noise
        lines = [
            f"IMU noise ({n['method']}): ARW {n['arw_dpsh']:.3g} deg/sqrt(h), "
            f"VRW {n['vrw_ugpsHz']:.3g} ug/sqrt(Hz)"
        ]
        if self.bias:
            lines.append(
                f"IMU bias on the still part: gyro about the vertical {self.bias['gyro_up_dph']:.3g} deg/h, "
                f"accelerometer along it {self.bias['accel_up_ug']:.3g} ug"
            )
        for r in self.runs:
            lines.append(
                f"in-process run with {r['grade']}: NIS per degree of freedom {r['nis_per_dof']:.2f} "
                f"({r['updates']} updates)"
            )
        lines.append(f"grade: {self.grade}" + (f" with {self.imu_overrides}" if self.imu_overrides else ""))
        if self.fixes:
            f = self.fixes
            lines.append(
                f"fixes {f['stream']!r}: sigma E/N/U {_v(f['sigma_enu_m'])} m ({f['origin']}), white scatter "
                f"{_v(f['white_enu_m'])} m"
            )
        if self.correlated:
            lines.append(
                f"correlated receiver error: sigma E/N/U {_v(self.correlated['sigma_enu_m'])} m, "
                f"{self.correlated['correlation_time_s']} s"
            )
        lines += self.notes
        return "\n".join(lines)


def _v(x) -> str:
    return "/".join(f"{float(a):.2f}" for a in x)


# --- IMU noise -------------------------------------------------------------------------------------
def allan_deviation(x: np.ndarray, dt: float, m_list) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation of rate samples ``x`` (interval ``dt``) at tau = m dt."""
    theta = np.concatenate([[0.0], np.cumsum(x) * dt])
    taus, adev = [], []
    for m in m_list:
        if 2 * m >= len(theta):
            break
        d = theta[2 * m :] - 2.0 * theta[m:-m] + theta[: -2 * m]
        tau = m * dt
        taus.append(tau)
        adev.append(math.sqrt(float(np.mean(d * d)) / (2.0 * tau * tau)))
    return np.array(taus), np.array(adev)


def white_density_in_motion(x: np.ndarray, dt: float, form: str = "increment") -> float:
    """White-noise density (unit/sqrt(Hz) of the rate, i.e. unit * sqrt(s)) from the robust scatter
    of second differences: smooth motion cancels, white noise of std s per sample gives sqrt(6) s.
    A rate-form source has been integrated by the trapezoid (replay/events.py ImuBuilder): each
    published rate is the mean of two neighbours, whose second difference has std s, not sqrt(6) s
    (the filter [1/2, 1/2] convolved with [1, -2, 1] is [1/2, -1/2, -1/2, 1/2])."""
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    gain = 1.0 if form == "rate" else math.sqrt(6.0)
    sigma = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / gain
    return sigma * math.sqrt(dt)


def still_parts(imu: ImuData, fx: FixData | None) -> tuple[int, int] | None:
    """The longest run of samples at rest (1 s blocks: specific-force scatter and rate small, the
    fixes' speed low where there are fixes), as (first, end) sample indices, if >= STILL_MIN_S."""
    w, f = imu.rates()
    dt = float(np.median(imu.dt))
    n = max(5, int(round(1.0 / dt)))
    blocks = len(imu) // n
    if blocks < 2:
        return None
    still = np.zeros(blocks, bool)
    v = fx.velocity() if fx is not None and len(fx) else None
    for b in range(blocks):
        sl = slice(b * n, (b + 1) * n)
        ok = (
            f[sl].std(axis=0).max() <= REST_ACCEL_STD_MPS2
            and np.linalg.norm(w[sl].mean(axis=0)) <= REST_RATE_RPS
        )
        if ok and v is not None:
            t0, t1 = imu.t[b * n], imu.t[(b + 1) * n - 1]
            near = (fx.t >= t0 - 0.5) & (fx.t <= t1 + 0.5)
            if near.any():
                ok = bool(np.all(np.hypot(v[near, 0], v[near, 1]) < STILL_SPEED_MPS))
        still[b] = ok
    best, run_start = (0, 0), None
    for b in range(blocks + 1):
        if b < blocks and still[b]:
            run_start = b if run_start is None else run_start
        elif run_start is not None:
            if b - run_start > best[1] - best[0]:
                best = (run_start, b)
            run_start = None
    if (best[1] - best[0]) * n * dt < STILL_MIN_S:
        return None
    return best[0] * n, best[1] * n


def imu_noise(imu: ImuData, fx: FixData | None, form: str = "increment") -> tuple[dict, dict | None]:
    """(noise figures, bias figures or None): module docstring, items 1 and 2."""
    w, f = imu.rates()
    dt = float(np.median(imu.dt))
    still = still_parts(imu, fx)
    if still is not None:
        a, b = still
        ws, fs = w[a:b], f[a:b]
        m1 = max(1, int(round(1.0 / dt)))
        ms = sorted({int(2**k) for k in range(0, 20)} | {m1})
        arw, vrw, binst_g, binst_a = [], [], [], []
        for j in range(3):
            tg, ag = allan_deviation(ws[:, j], dt, ms)
            ta, aa = allan_deviation(fs[:, j], dt, ms)
            arw.append(float(np.interp(1.0, tg, ag)))  # sigma(1 s) = N for white noise
            vrw.append(float(np.interp(1.0, ta, aa)))
            binst_g.append(float(ag.min()) / 0.664)
            binst_a.append(float(aa.min()) / 0.664)
        lat = math.radians(float(fx.lat_deg[0])) if fx is not None and len(fx) else 0.0
        h = float(fx.h_m[0]) if fx is not None and len(fx) else 0.0
        f_mean, w_mean = fs.mean(axis=0), ws.mean(axis=0)
        up = f_mean / np.linalg.norm(f_mean)
        omega_up = earth.OMEGA_IE_RPS * math.sin(lat)
        bias = {
            "still_s": float((b - a) * dt),
            "gyro_up_dph": abs(float(w_mean @ up) - omega_up) / earth.DPH,
            "accel_up_ug": abs(float(np.linalg.norm(f_mean)) - earth.gravity_normal(lat, h)) / earth.UG,
            "latitude_known": fx is not None and len(fx) > 0,
        }
        noise = {
            "method": f"Allan deviation on a still part of {bias['still_s']:.0f} s (sigma at tau = 1 s)",
            "arw_dpsh": max(arw) * DPSH_PER_RPSS,
            "vrw_ugpsHz": max(vrw) / earth.UG,
            "gyro_bias_instability_dph": max(binst_g) / earth.DPH,
            "accel_bias_instability_ug": max(binst_a) / earth.UG,
        }
        return noise, bias
    arw = [white_density_in_motion(w[:, j], dt, form) for j in range(3)]
    vrw = [white_density_in_motion(f[:, j], dt, form) for j in range(3)]
    noise = {
        "method": "sample-to-sample scatter in motion (no still part of "
        f"{STILL_MIN_S:.0f} s: vibration counts as noise)",
        "arw_dpsh": max(arw) * DPSH_PER_RPSS,
        "vrw_ugpsHz": max(vrw) / earth.UG,
    }
    return noise, None


def covering_grades(noise: dict, bias: dict | None) -> list[str]:
    """Grades (best first) whose numbers cover the measurements (module docstring, item 3)."""
    out = []
    for g in ORDER:
        p = PRESETS[g]
        ok = (
            noise["arw_dpsh"] <= NOISE_MARGIN * p.arw_dpsh
            and noise["vrw_ugpsHz"] <= NOISE_MARGIN * p.vrw_ugpsHz
        )
        if bias is not None:
            ok = ok and bias["gyro_up_dph"] <= BIAS_MARGIN * max(p.gyro_bias_dph, 1.0)
            ok = ok and bias["accel_up_ug"] <= BIAS_MARGIN * p.accel_bias_ug
        if ok:
            out.append(g)
    return out


def consumer_overrides(noise: dict, bias: dict | None) -> tuple[dict[str, float], dict[str, str]]:
    """An IMU no preset covers: the consumer_mems numbers raised to the measurement (noise x 1.25,
    biases as measured), and per number what was done (its comment in the written file)."""
    p = PRESETS["consumer_mems"]
    # field: (measured, margin, digits): the larger of the preset's number and margin x measured
    measured = {"arw_dpsh": (noise["arw_dpsh"], 1.25, 4), "vrw_ugpsHz": (noise["vrw_ugpsHz"], 1.25, 2)}
    if bias is not None:
        measured["gyro_bias_dph"] = (bias["gyro_up_dph"], 1.0, 1)
        measured["accel_bias_ug"] = (bias["accel_up_ug"], 1.0, 0)
    overrides, why = {}, {}
    for k, (m, margin, digits) in measured.items():
        preset = getattr(p, k)
        overrides[k] = round(max(preset, margin * m), digits)
        times = f" x {margin}" if margin != 1.0 else ""
        why[k] = (
            f"measured {m:.3g}{times} (above the preset's {preset})"
            if margin * m > preset
            else f"the preset's: measured {m:.3g}{times} is below it"
        )
    return overrides, why


# --- the in-process run -------------------------------------------------------------------------------
class _Collect:
    """Engine sink keeping each pipeline's (t, position ENU-ready llh, velocity)."""

    def __init__(self):
        self.t: list[float] = []
        self.llh: list[tuple[float, float, float]] = []
        self.vel: list[np.ndarray] = []

    def on_estimate(self, vehicle, out) -> None:
        nav = out.est.nav
        self.t.append(float(nav.t))
        self.llh.append((nav.lat_rad, nav.lon_rad, nav.h_m))
        self.vel.append(np.asarray(nav.vel_enu_mps, float).copy())

    def on_output(self, vehicle, msg, err9=None) -> None:
        pass

    def on_truth(self, vehicle, truth) -> None:
        pass


def run_in_process(mapping: ReplayMapping, base: Path, grade: str, overrides: dict | None = None) -> dict:
    """The service's engine (one loosely coupled pipeline, fixes as independent, no lever arm) on
    the log's first RUN_S seconds with IMU ``grade``: NIS per degree of freedom after SETTLE_S
    from its first aiding, and the solutions (for the fixes' white scatter)."""
    from fednav.service import keys
    from fednav.service.config import from_dict
    from fednav.service.vehicle import VehicleLoop

    cfg = from_dict(
        {
            "prefix": mapping.prefix,
            "vehicles": [mapping.vehicle],
            "init": {"mode": "auto", "align_time_s": 10.0, "min_speed_mps": 3.0},
            "imu": {"grade": grade, **(overrides or {})},
            "pipelines": [{"name": "lc", "kind": "loosely_coupled"}],
        },
        "suggest-config run",
    )
    sink = _Collect()
    loop = VehicleLoop(mapping.vehicle, cfg, sink)
    t0 = None
    for ev in all_events(mapping, base):
        t0 = ev.t_gps_s if t0 is None else t0
        if ev.t_gps_s - t0 > RUN_S:
            break
        pk = keys.parse_input(f"{mapping.prefix}/{mapping.vehicle}/{ev.key_suffix}", mapping.prefix)
        loop.process(pk.kind, pk.sensor_id, ev.msg)
    pipe = loop.engine.pipelines[0]
    hist = list(getattr(pipe, "nis_history", []))
    first = hist[0][0] if hist else None
    use = [(nis, dof) for t, _, nis, dof in hist if first is not None and t - first >= SETTLE_S]
    nis = sum(n for n, _ in use) / max(sum(d for _, d in use), 1)
    return {
        "grade": grade,
        "nis_per_dof": float(nis) if use else float("nan"),
        "updates": len(use),
        "refused": int(sum(pipe.screened.values())) if hasattr(pipe, "screened") else 0,
        "solutions": sink,
    }


# --- fixes -----------------------------------------------------------------------------------------------
def white_scatter(fx: FixData, sol: _Collect) -> np.ndarray | None:
    """Per ENU axis, the fixes' white noise: the scatter of consecutive fix differences minus the
    solution's displacement between them (its velocity integrated), / sqrt(2)."""
    if len(sol.t) < 10 or len(fx) < 10:
        return None
    ts = np.array(sol.t)
    vel = np.array(sol.vel)
    p = fx.enu()
    step = float(np.median(np.diff(fx.t)))
    d = []
    for k in range(1, len(fx)):
        a, b = fx.t[k - 1], fx.t[k]
        if b - a > 1.5 * step or a < ts[0] + SETTLE_S or b > ts[-1]:
            continue
        grid = np.linspace(a, b, 5)
        v = np.stack([np.interp(grid, ts, vel[:, j]) for j in range(3)], axis=1)
        disp = np.trapezoid(v, grid, axis=0)
        d.append(p[k] - p[k - 1] - disp)
    if len(d) < 10:
        return None
    d = np.array(d)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / math.sqrt(2.0)


# --- the suggestion ----------------------------------------------------------------------------------------
def suggest_config(mapping: ReplayMapping, base_dir: Path, report: Report) -> Suggestion:
    """Estimate and write (module docstring). ``report``: the checks' report (decoded data)."""
    imu_idx = next((i for i, s in enumerate(mapping.streams) if s.kind == "imu" and i in report.data), None)
    if imu_idx is None:
        raise SuggestError("the log has no readable IMU stream")
    fix_idx = next(
        (i for i, s in enumerate(mapping.streams) if s.kind == "gnss_fix" and i in report.data), None
    )
    if fix_idx is None:
        raise SuggestError("a GNSS fix stream is needed (the in-process run aligns and aids on it)")
    imu: ImuData = report.data[imu_idx]
    fx: FixData = report.data[fix_idx]
    istream = mapping.streams[imu_idx]
    form = "rate" if istream.resolved_format() == "ubx" else istream.form
    noise, bias = imu_noise(imu, fx, form)
    covering = covering_grades(noise, bias)
    runs: list[dict] = []
    overrides: dict[str, float] = {}
    why: dict[str, str] = {}
    notes: list[str] = []
    if covering:
        candidates = [g for g in ORDER if ORDER.index(g) >= ORDER.index(covering[0])]
    else:  # worse than every preset: consumer numbers raised to the measurement
        candidates = ["consumer_mems"]
        overrides, why = consumer_overrides(noise, bias)
        notes.append(
            "the IMU is not covered by the consumer_mems preset: each [imu] number is the larger of the "
            "preset's and the measured one (noise x 1.25)"
        )
    # the in-process runs: the most cautious grade first (its innovations only reflect how the
    # fixes are modelled), then the best covering grade, one lower at a time while its innovations
    # are clearly larger than the cautious grade's (its bias model trusts the IMU too much)
    base_grade = "consumer_mems"
    cautious = run_in_process(mapping, base_dir, base_grade, overrides)
    runs.append({k: v for k, v in cautious.items() if k != "solutions"})
    if not math.isfinite(cautious["nis_per_dof"]):
        raise SuggestError(
            "the in-process run was never aided: the engine needs a fix in motion above 3 m/s (or a rest "
            "of 10 s) to start; check the checks' time offsets"
        )
    grade, run = base_grade, cautious
    for g in candidates:
        if g == base_grade:
            break
        r = run_in_process(mapping, base_dir, g)
        runs.append({k: v for k, v in r.items() if k != "solutions"})
        ok = (
            math.isfinite(r["nis_per_dof"])
            and r["nis_per_dof"] <= NIS_LIMIT
            and r["nis_per_dof"] <= NIS_RELATIVE * cautious["nis_per_dof"]
        )
        if ok:
            grade, run = g, r
            break
    if cautious["nis_per_dof"] > NIS_LIMIT:
        notes.append(
            f"even {base_grade} leaves the innovations {cautious['nis_per_dof']:.1f}x their expected size: "
            "check the mapping (axes, time offset) and the fix sigmas"
        )
    # fixes
    fstream = mapping.streams[fix_idx]
    sr = report.streams[fix_idx]
    sig = sr.sigma or {}
    sigma = np.array(sig.get("pos_std_enu_m_median", [float("nan")] * 3))
    origin = ", ".join(f"{k}: {n} fixes" for k, n in sig.get("pos_origin", {}).items()) or "unknown"
    white = white_scatter(fx, run["solutions"])
    fixes = {
        "stream": fstream.sensor_id,
        "sigma_enu_m": sigma.tolist(),
        "origin": origin,
        "white_enu_m": None if white is None else white.tolist(),
    }
    correlated = None
    if white is not None:
        ratio = sigma / np.maximum(white, 1e-3)
        fixes["sigma_over_white"] = ratio.tolist()
        if np.any(ratio < 1.0 / WHITE_ONLY_RATIO):
            notes.append(
                f"the fixes scatter {_v(white)} m from one to the next, more than the sigma they carry "
                f"({_v(sigma)} m): the filter will trust them too much"
                + (
                    f"; set pos_std_m = [{', '.join(f'{x:.2f}' for x in np.maximum(white, sigma))}] "
                    "in stream "
                    f"{fstream.sensor_id!r}"
                    if "default" in sig.get("pos_origin", {}) or "mapping" in sig.get("pos_origin", {})
                    else " (the receiver's own sigmas: the mapping's pos_std_m only replaces missing ones)"
                )
            )
        elif np.all(np.isfinite(sigma)):  # (sigmas too small: fix them first, then the correlated part)
            floor = MIN_CORRELATED_FRACTION * sigma
            gm = np.sqrt(np.maximum(sigma**2 - white**2, floor**2))
            at_floor = sigma**2 - white**2 < floor**2
            fixes["correlated_floor_axes"] = [a for a, f in zip("ENU", at_floor, strict=True) if f]
            correlated = {
                "sigma_enu_m": [round(float(x), 3) for x in gm],
                "correlation_time_s": DEFAULT_TAU_S,
            }
    sug = Suggestion(
        grade, overrides, noise, bias, runs, fixes, correlated, notes=notes, imu_override_why=why
    )
    sug.toml = render_toml(mapping, sug)
    from fednav.service.config import from_dict

    from_dict(tomllib.loads(sug.toml), "the suggested configuration")  # it must load
    return sug


def render_toml(mapping: ReplayMapping, s: Suggestion) -> str:
    n = s.noise
    p = PRESETS[s.grade]
    lines = [
        "# fednav-service configuration suggested by fednav-replay --suggest-config from the log itself:",
        "# every number says where it came from. Start the service with --config <this file>.",
        f'prefix = "{mapping.prefix}"',
        f'vehicles = ["{mapping.vehicle}"]   # the mapping\'s vehicle',
        "",
        "[init]",
        'mode = "auto"               # at rest for align_time_s: static alignment; else from a fix in motion',
        "align_time_s = 20.0         # seconds at rest for a static alignment when the log starts at rest",
        "                            # (the example files' value); in motion it aligns from a fix",
        "min_speed_mps = 3.0         # a car's course is usable above ~3 m/s",
        "",
        "[imu]",
        f'grade = "{s.grade}"' + " " * max(1, 22 - len(s.grade)) + "# docs/imu_grades.md; why:",
        f"#   noise: {n['method']}: ARW {n['arw_dpsh']:.3g} deg/sqrt(h) (preset {p.arw_dpsh}), VRW "
        f"{n['vrw_ugpsHz']:.3g} ug/sqrt(Hz) (preset {p.vrw_ugpsHz})",
    ]
    if "gyro_bias_instability_dph" in n:
        lines.append(
            "#   bias instability (Allan floor / 0.664): gyro "
            f"{n['gyro_bias_instability_dph']:.3g} deg/h (preset "
            f"{p.gyro_bias_instability_dph}), accelerometer {n['accel_bias_instability_ug']:.3g} ug (preset "
            f"{p.accel_bias_instability_ug})"
        )
    if s.bias:
        lines.append(
            f"#   bias on the still part: gyro about the vertical {s.bias['gyro_up_dph']:.3g} deg/h "
            f"(preset sigma {p.gyro_bias_dph}), accelerometer along it {s.bias['accel_up_ug']:.3g} ug "
            f"(preset sigma {p.accel_bias_ug})"
        )
    for r in s.runs:
        lines.append(
            f"#   in-process run of the first {RUN_S:.0f} s with {r['grade']}: NIS per degree of freedom "
            f"{r['nis_per_dof']:.2f} over {r['updates']} updates"
        )
    lines.append(
        f"#   (a grade better than consumer_mems is kept when its NIS stays below {NIS_LIMIT} and within "
        f"{NIS_RELATIVE}x consumer_mems')"
    )
    for k, v in s.imu_overrides.items():
        lines.append(f"{k} = {v}   # {s.imu_override_why.get(k, 'measured')}")
    lines += [
        "",
        "[[pipelines]]",
        'name = "lc"',
        'kind = "loosely_coupled"',
        "# antenna position from the IMU in the body frame (right, forward, up), m: NOT estimated from the",
        "# log, measure it (a roof antenna 1 m ahead of and 1.2 m above a dashboard phone: [0.0, 1.0, 1.2])",
        "gnss_lever_arm_b_m = [0.0, 0.0, 0.0]",
    ]
    f = s.fixes
    lines.append(
        f"# fixes of stream {f['stream']!r}: sigma E/N/U {_v(f['sigma_enu_m'])} m "
        f"(median; from {f['origin']})"
        + (
            f", white scatter {_v(f['white_enu_m'])} m (fix-to-fix against the solution's displacement)"
            if f["white_enu_m"]
            else ""
        )
    )
    if s.correlated:
        c = s.correlated
        below = [a for a, r in zip("ENU", f.get("sigma_over_white", ()), strict=False) if not r > 1.0]
        if below:  # (a sigma more than WHITE_ONLY_RATIO x below it would give a note, no states)
            above = [a for a in "ENU" if a not in below]
            lines += [
                f"# the fixes' sigma does not exceed their white scatter on {'/'.join(below)} (it is less "
                f"than {WHITE_ONLY_RATIO}x below it);",
                f"# on {'/'.join(above)} it does: the rest is a slowly varying error,"
                if above
                else "# a slowly varying error is modelled all the same,",
            ]
        else:
            lines.append(
                "# the fixes' sigma exceeds their white scatter: the rest is a slowly varying error,"
            )
        lines += [
            "# estimated as states (docs/own_data.md); sigma = sqrt(fix sigma^2 - white^2) per axis",
            f"# and at least {MIN_CORRELATED_FRACTION:.0%} of the fix sigma (real receivers' errors are "
            "correlated; at 10 Hz even a",
            "# small correlated part, fused as independent, makes the filter overconfident)"
            + (
                f": that floor on {'/'.join(f['correlated_floor_axes'])};"
                if f.get("correlated_floor_axes")
                else ";"
            ),
            "# correlation time: the value measured on real receivers (docs/own_data.md: 31-42 s),",
            "# not measurable from a short log",
            f"gnss_correlated_error = {{ sigma_enu_m = [{', '.join(str(x) for x in c['sigma_enu_m'])}], "
            f"correlation_time_s = {c['correlation_time_s']} }}",
        ]
    elif f["white_enu_m"]:
        lines.append("# (the fixes carry no usable sigma: no correlated-error states)")
    else:
        lines.append("# (the fixes' scatter could not be measured: no correlated-error states)")
    for note in s.notes:
        lines.append(f"# note: {note}")
    return "\n".join(lines) + "\n"
