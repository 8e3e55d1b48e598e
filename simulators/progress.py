"""Progress bar of ``fednav-sim eval`` (tqdm): scenario seconds of all Monte Carlo runs.

Shown only on a terminal (stderr is a tty) and without ``--json``; otherwise every call is a
no-op, so logs and pipes stay clean.
"""

from __future__ import annotations

from fednav.simulators.scenario import Scenario


class EvalProgress:
    """One bar over ``runs x duration_s`` seconds of scenario time, labelled with the run."""

    def __init__(self, scenario: Scenario, runs: int, enabled: bool, file=None):
        self.enabled = enabled
        self.duration_s = float(scenario.duration_s)
        self.runs = runs
        self._t0 = float(scenario.t0_gps_s)  # every run starts at the scenario's start
        self._done = 0.0
        self._bar = None
        if enabled:
            from tqdm import tqdm

            self._bar = tqdm(
                total=round(runs * self.duration_s),
                unit="s",
                desc=f"{scenario.name} run 1/{runs}",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} scenario s "
                "[{elapsed}<{remaining}, {rate_fmt}]",
                leave=False,
                dynamic_ncols=True,
                file=file,
                mininterval=0.5,
            )

    def at(self, run_index: int, t_s: float) -> None:
        """Sensor time ``t_s`` reached in run ``run_index`` (0-based)."""
        if self._bar is None:
            return
        done = run_index * self.duration_s + min(max(t_s - self._t0, 0.0), self.duration_s)
        step = round(done) - self._bar.n
        if step > 0:
            self._bar.update(step)

    def run_done(self, i: int, runs: int, wall_s: float) -> None:
        """Run ``i`` (1-based) finished after ``wall_s`` seconds."""
        if self._bar is None:
            return
        step = round(i * self.duration_s) - self._bar.n
        if step > 0:
            self._bar.update(step)
        if i < runs:
            self._bar.set_description_str(f"{self.desc_name} run {i + 1}/{runs}")

    @property
    def desc_name(self) -> str:
        return (self._bar.desc or "").split(" run ")[0] if self._bar is not None else ""

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
