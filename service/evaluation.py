"""Errors against truth and their statistics: one module for the engine, the recording and eval.

The 9 navigation errors (computed minus true) are in the error-state convention of
:mod:`service.ins.error_model`: ``[dp_enu_m, dv_enu_mps, phi_rad]``; their public names (eval
JSON, recording entities, Solution sigmas) are the one table ``error_model.NAV_ERRORS``.

- :func:`nav_errors` / :func:`errors_against_truth`: the error vector of a navigation state.
- :func:`nees`: e' P^-1 e against the filter's own 9x9 covariance.
- :func:`report_errors`, :func:`error_stats`: named errors and RMS / max for ``fednav-sim eval``.
- :func:`recording_errors`: errors and 3-sigma bounds under the recording's names.
- :func:`fault_window_max_vel`, :func:`integrity_metrics`: the seed 000 fault-window figure and
  the seed 001 integrity classes (the paper's Table 1), on plain fault windows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fednav.service import earth
from fednav.service.estimation.integrity.monitor import limits
from fednav.service.ins.error_model import NAV_ERRORS
from fednav.service.ins.mechanisation import NavState
from fednav.service.messages import Integrity, Truth

#: eval report keys, in the order of the printed tables (north, east, up, then velocity, attitude)
REPORT_KEYS = tuple(NAV_ERRORS[i].report for i in (1, 0, 2, 3, 4, 5, 6, 7, 8))
RECORDING_NAMES = tuple(n.recording for n in NAV_ERRORS)
_PER_SI = np.array([n.per_si for n in NAV_ERRORS])
_REPORT_INDEX = np.array([1, 0, 2, 3, 4, 5, 6, 7, 8])


def nav_errors(
    nav: NavState, truth_llh: np.ndarray, truth_vel: np.ndarray, truth_mat_nb: np.ndarray
) -> np.ndarray:
    """Errors (computed minus true), (9,): [dp_enu_m, dv_enu_mps, phi_rad].

    phi from C_computed = (I - [phi x]) C_true, i.e. phi = rotation vector of C_true C_computed'.
    """
    r_m, r_n = earth.radii(truth_llh[0])
    dp = np.array(
        [
            earth.wrap_pi(nav.lon_rad - truth_llh[1]) * (r_n + truth_llh[2]) * math.cos(truth_llh[0]),
            (nav.lat_rad - truth_llh[0]) * (r_m + truth_llh[2]),
            nav.h_m - truth_llh[2],
        ]
    )
    dv = nav.vel_enu_mps - truth_vel
    phi = earth.quat_to_rotvec(earth.mat_to_quat(truth_mat_nb @ nav.mat_nb.T))
    return np.concatenate([dp, dv, phi])


def errors_against_truth(nav: NavState, truth: Truth) -> np.ndarray:
    """:func:`nav_errors` against a Truth message (same epoch)."""
    llh = np.array([math.radians(truth.lat_deg), math.radians(truth.lon_deg), truth.height_m])
    c_nb = earth.rpy_to_mat_nb(earth.rpy_from_msg_deg(truth.rpy_deg))
    return nav_errors(nav, llh, np.asarray(truth.vel_enu_mps), c_nb)


def nees(e9: np.ndarray, P9: np.ndarray) -> float:
    """Normalised estimation error squared e' P^-1 e (Cholesky solve; raises LinAlgError if P is
    not positive definite)."""
    L = np.linalg.cholesky(P9)
    w = np.linalg.solve(L, e9)
    return float(w @ w)


def report_errors(e9: np.ndarray) -> dict[str, float]:
    """Named errors for reports (``REPORT_KEYS``: lat_m = north, lon_m = east, ..., arcsec)."""
    v = np.asarray(e9, dtype=float) * _PER_SI
    return {NAV_ERRORS[i].report: float(v[i]) for i in _REPORT_INDEX}


def error_stats(err: np.ndarray) -> tuple[dict[str, float], dict[str, float]]:
    """RMS and max |.| of errors (N, 9) per report key."""
    v = np.asarray(err, dtype=float)[:, _REPORT_INDEX] * _PER_SI[_REPORT_INDEX]
    rms = np.sqrt(np.mean(v * v, axis=0))
    mx = np.max(np.abs(v), axis=0)
    return (
        {k: float(x) for k, x in zip(REPORT_KEYS, rms, strict=True)},
        {k: float(x) for k, x in zip(REPORT_KEYS, mx, strict=True)},
    )


def recording_errors(e9: np.ndarray, P9: np.ndarray) -> tuple[dict[str, float], dict[str, float]]:
    """Errors and their 3-sigma bounds under the recording's names (attitude in arcsec)."""
    sd = np.sqrt(np.clip(np.diagonal(P9), 0.0, None))
    v = np.asarray(e9, dtype=float) * _PER_SI
    b = 3.0 * sd * _PER_SI
    return (
        {n: float(x) for n, x in zip(RECORDING_NAMES, v, strict=True)},
        {n: float(x) for n, x in zip(RECORDING_NAMES, b, strict=True)},
    )


# --- fault windows -------------------------------------------------------------------------------
@dataclass(frozen=True)
class FaultWindow:
    """An injected fault, in seconds from the scenario start: [start_s, end_s), the sensor it
    affects, its aiding period (the first filter cycle of a window is not judged) and, for raw
    GNSS faults, the satellites."""

    start_s: float
    end_s: float
    sensor: str = ""
    cycle_s: float = 1.0
    satellites: frozenset[str] = frozenset()


def fault_window_max_vel(windows: list[FaultWindow], t_rel: np.ndarray, err: np.ndarray) -> float | None:
    """Largest velocity-error norm inside the fault windows, after the first filter cycle of each
    (seed 000: "velocity error corrected to within 0.2 m/s in all fault windows")."""
    if not windows:
        return None
    vnorm = np.linalg.norm(np.asarray(err)[:, 3:6], axis=1)
    worst = 0.0
    for f in windows:
        sel = (t_rel >= f.start_s + f.cycle_s - 1e-6) & (t_rel < f.end_s)
        if sel.any():
            worst = max(worst, float(vnorm[sel].max()))
    return worst


# --- end errors and private states (seed 004) ----------------------------------------------------
def dvl_state_summary(runs: list[dict]) -> dict:
    """Per DVL state over the runs: RMS of (estimate - truth) at the end, mean 1-sigma, and the
    mean normalised squared error (1 when the sigma is consistent)."""
    out = {}
    for name in runs[0]:
        e = np.array([r[name][0] for r in runs])
        sd = np.array([r[name][1] for r in runs])
        out[name] = {
            "rms_error": float(np.sqrt(np.mean(e**2))),
            "sigma": float(np.mean(sd)),
            "nees": float(np.mean((e / np.maximum(sd, 1e-300)) ** 2)),
        }
    return out


def end_errors(ends: list[np.ndarray]) -> dict:
    """Errors at the last solution epoch of each run: horizontal position and velocity error norms
    (mean and max over runs) and the mean signed east/north components (seed 004's Table 3)."""
    if not ends:
        return {}
    e = np.array(ends)
    pos = np.hypot(e[:, 0], e[:, 1])
    vel = np.hypot(e[:, 3], e[:, 4])
    return {
        "end_pos_m": float(pos.mean()),
        "end_pos_m_max": float(pos.max()),
        "end_vel_mps": float(vel.mean()),
        "end_vel_mps_max": float(vel.max()),
        "end": {
            "east_m": float(e[:, 0].mean()),
            "north_m": float(e[:, 1].mean()),
            "ve_mps": float(e[:, 3].mean()),
            "vn_mps": float(e[:, 4].mean()),
        },
    }


# --- integrity (seed 001): per-epoch classes of the paper's Table 1 ------------------------------
INTEGRITY_CLASSES = ("normal", "detected", "missed", "false_alarm", "undetected")


def integrity_metrics(
    faults: list[FaultWindow],
    t0_s: float,
    rate_hz: float,
    runs: list[list[tuple[Integrity, np.ndarray | None]]],
) -> dict:
    """Integrity figures of one pipeline over runs of one scenario (JSON-ready).

    ``faults``: the raw-GNSS fault windows in onset order; ``t0_s``: the scenario start (GPS s);
    ``rate_hz``: the IMU rate (message times are put on its grid). Epochs are the pipeline's
    Integrity messages (one per GNSS epoch); ``t_rel`` is the message time from the scenario
    start. A fault is *active* at ``start_s <= t_rel < end_s``. Per fault, the epoch is *flagged*
    when the message has ``detected`` or ``alarm``, or lists one of the fault's satellites in
    ``excluded``; the fault is *detected in time* when its first flagged epoch inside its window
    comes at most TTA (the phase's time to alert) after its onset. herr = true horizontal error
    of the solution at the epoch (|dp_east, dp_north|); hazardous = herr > HPL or herr > HAL.

    Classes (each epoch exactly one; the paper's Table 1 plus "undetected"):
      normal       no fault active, neither detected nor alarm
      false_alarm  no fault active, detected or alarm (exclusions kept from earlier faults do not
                   count; a detection caused by the filter's recovery right after a fault ends does)
      detected     fault active, flagged, and that fault was detected in time
      missed       fault active and either flagged only after TTA, or not flagged while hazardous
                   and that fault was not detected in time (never, or late)
      undetected   fault active, not flagged, not hazardous -- or hazardous while a detection in
                   time is still to come (then also counted in hmi_epochs if herr > HPL)
    Overlay (not a class): hmi_epochs = herr > HPL with no alarm, at any epoch; also reported as
    ``counts["hmi"]``. The classes (all counts but "hmi") sum to ``epochs``.
    p_fa = false_alarm / (normal + false_alarm) (per fault-free epoch; the paper's 1.25e-4 is
    1 / 8000 over all epochs), p_md = missed / (detected + missed +
    undetected) (per fault epoch). detection_latency_s: first epoch flagged (detected, alarm or an
    exclusion listed) at or after the first fault's onset, minus that onset; with several runs the
    worst run (per-run values in ``detection_latency_runs_s``). ``excluded_satellites``: every
    satellite excluded at some epoch. ``healthy_exclusions``: exclusions of a satellite that no
    fault touched at the time (its first epoch in ``excluded`` outside every window of a fault on
    it, and more than TTA after the end of the last one), each as {run, t_s, satellite}, and
    ``healthy_exclusion_count`` -- the
    classes do not show them (an epoch with the faulty satellite excluded is ``detected`` whatever
    else is excluded), and each costs the solution a good satellite until it is re-admitted.
    Epochs without truth are counted in ``epochs_without_truth`` and classified without the error
    criteria (never hazardous, never HMI).
    """
    rate, t0 = rate_hz, t0_s
    counts = dict.fromkeys(INTEGRITY_CLASSES, 0)
    hpl, vpl, latencies = [], [], []
    hmi = alarms = no_truth = n_ep = 0
    excluded: set[str] = set()
    healthy: list[dict] = []
    fault_latency: list[float | None] = []
    for run, pairs in enumerate(runs):
        t_rel = [round((m.t - t0) * rate) / rate for m, _ in pairs]
        # first flagged epoch of each fault inside its window
        first_flag: list[float | None] = []
        for s0, s1, sats in [(f.start_s, f.end_s, f.satellites) for f in faults]:
            first_flag.append(
                next(
                    (
                        t
                        for t, (m, _) in zip(t_rel, pairs, strict=True)
                        if s0 <= t < s1 and (m.detected or m.alarm or sats & set(m.excluded))
                    ),
                    None,
                )
            )
        fault_latency += [
            None if f is None else f - w.start_s for f, w in zip(first_flag, faults, strict=True)
        ]
        if faults:
            on = faults[0].start_s
            det = next(
                (t for t, (m, _) in zip(t_rel, pairs, strict=True) if t >= on and (m.detected or m.alarm)),
                None,
            )
            latencies.append(None if det is None else det - on)
        before: set[str] = set()
        for t, (m, e) in zip(t_rel, pairs, strict=True):
            n_ep += 1
            tta = limits(m.phase).tta_s
            now = set(m.excluded)
            for sat in sorted(now - before):
                if not any(sat in w.satellites and w.start_s <= t < w.end_s + tta for w in faults):
                    healthy.append({"run": run, "t_s": t, "satellite": sat})
            before = now
            hpl.append(m.hpl_m)
            vpl.append(m.vpl_m)
            alarms += bool(m.alarm)
            excluded |= set(m.excluded)
            herr = None if e is None else math.hypot(float(e[0]), float(e[1]))
            no_truth += herr is None
            hazardous = herr is not None and (herr > m.hpl_m or herr > m.hal_m)
            if herr is not None and herr > m.hpl_m and not m.alarm:
                hmi += 1
            active = [i for i, w in enumerate(faults) if w.start_s <= t < w.end_s]
            if not active:
                counts["false_alarm" if (m.detected or m.alarm) else "normal"] += 1
                continue
            i = active[0]
            sats = set().union(*(faults[j].satellites for j in active))
            in_time = first_flag[i] is not None and first_flag[i] - faults[i].start_s <= tta + 1e-9
            if m.detected or m.alarm or sats & set(m.excluded):
                counts["detected" if in_time else "missed"] += 1
            elif hazardous and not in_time:
                counts["missed"] += 1
            else:
                counts["undetected"] += 1
    fault_free = counts["normal"] + counts["false_alarm"]
    faulty = counts["detected"] + counts["missed"] + counts["undetected"]
    counts["hmi"] = hmi  # the paper's HMI column: an overlay on the classes, not summed with them
    lat_known = [x for x in latencies if x is not None]

    def stats(v: list[float]) -> dict:
        return (
            {"median": float(np.median(v)), "max": float(np.max(v))} if v else {"median": None, "max": None}
        )

    return {
        "epochs": n_ep,
        "detection_latency_s": (max(lat_known) if len(lat_known) == len(latencies) else None)
        if latencies
        else None,
        "detection_latency_runs_s": latencies,
        "hpl_m": stats(hpl),
        "vpl_m": stats(vpl),
        "hmi_epochs": hmi,
        "alarms": alarms,
        "counts": counts,
        "p_fa": counts["false_alarm"] / fault_free if fault_free else None,
        "p_md": counts["missed"] / faulty if faulty else None,
        "faults": len(faults) * len(runs),
        "faults_detected_in_time": sum(1 for x in fault_latency if x is not None and x <= _tta(runs) + 1e-9),
        "fault_latency_s": stats([x for x in fault_latency if x is not None]),
        "excluded_satellites": sorted(excluded),
        "healthy_exclusion_count": len(healthy),
        "healthy_exclusions": healthy,
        "epochs_without_truth": no_truth,
    }


def _tta(runs: list) -> float:
    for pairs in runs:
        for m, _ in pairs:
            return limits(m.phase).tta_s
    return math.inf
