"""Fault injection shared by every simulated sensor (and, later, by individual satellites).

A fault acts on named channels of one sensor during ``[start_s, start_s + duration_s)`` (times
relative to the scenario start). Channel values are in the channel's own units (m, m/s, arcsec...);
which quantity a channel carries is the sensor model's choice, documented there (for additive
faults it does not matter; ``scale`` multiplies whatever the sensor passes).

Kinds (``tau = t - start_s``, per channel ``c``)::

    step         x + magnitude[c]
    ramp         x + rate_per_s[c] * tau
    noise        x + mean[c] + std[c] * n,  n ~ N(0, 1) fresh at every call
    random_walk  x + w_c(t),  w_c(start) = 0, w_c(t2) - w_c(t1) ~ N(0, sigma[c]^2 (t2 - t1))
    oscillation  x + amplitude[c] * sin(2 pi freq_hz[c] tau + phase_rad[c])
    scale        x * factor[c]
    outliers     isolated outliers (He, Nie, Wu 2011, section 5) on the published channels
                 matching ``channels`` (fnmatch patterns, e.g. ``"*.pseudorange"``):
                 ``per = "epoch"``: at each sensor epoch in the window, with probability
                 ``fraction``, ``per_epoch`` of them drawn uniformly; ``per = "channel"``: each
                 of them independently with probability ``fraction``. A hit channel gets
                 sign * k * sigma, k drawn uniformly from ``multiples``, random sign. The hit
                 channels are listed by :meth:`FaultSet.active` at exactly those epochs.

Faults apply in the order they are listed. Each fault owns a child generator spawned from the
``rng`` given to :class:`FaultSet`, so its draws do not depend on the other faults.
"""

from __future__ import annotations

import math
from fnmatch import fnmatchcase
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from fednav.service.messages import ActiveFault


class _FaultBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    sensor: str = Field(min_length=1, description="Sensor the fault acts on, e.g. 'gnss', 'star'")
    start_s: float = Field(ge=0.0, description="Onset, s after the scenario start")
    duration_s: float = Field(
        gt=0.0, description="Length of the active window [start_s, start_s + duration_s), s"
    )
    channels: list[str] = Field(min_length=1, description="Channels affected, e.g. ['pos_e', 'vel_n']")

    _params: ClassVar[tuple[str, ...]] = ()  # names of the per-channel parameter lists

    @model_validator(mode="after")
    def _lengths(self):
        if len(set(self.channels)) != len(self.channels):
            raise ValueError(f"channels has duplicates: {self.channels}")
        for p in self._params:
            v = getattr(self, p)
            if len(v) != len(self.channels):
                raise ValueError(
                    f"{p} has {len(v)} values but channels has {len(self.channels)} ({self.channels}); "
                    "give one value per channel"
                )
        return self

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def is_active(self, t_rel_s: float) -> bool:
        return self.start_s <= t_rel_s < self.start_s + self.duration_s


class StepFault(_FaultBase):
    kind: Literal["step"]
    magnitude: list[float] = Field(description="Offset added per channel, channel units")
    _params: ClassVar[tuple[str, ...]] = ("magnitude",)


class RampFault(_FaultBase):
    kind: Literal["ramp"]
    rate_per_s: list[float] = Field(description="Offset growth rate per channel, channel units per s")
    _params: ClassVar[tuple[str, ...]] = ("rate_per_s",)


class NoiseFault(_FaultBase):
    kind: Literal["noise"]
    mean: list[float] = Field(description="Mean of the added white noise per channel, channel units")
    std: list[Annotated[float, Field(ge=0.0)]] = Field(description="Std of the added white noise per channel")
    _params: ClassVar[tuple[str, ...]] = ("mean", "std")


class RandomWalkFault(_FaultBase):
    kind: Literal["random_walk"]
    sigma_per_sqrt_s: list[Annotated[float, Field(ge=0.0)]] = Field(
        description="Random-walk intensity per channel, channel units per sqrt(s)"
    )
    _params: ClassVar[tuple[str, ...]] = ("sigma_per_sqrt_s",)


class OscillationFault(_FaultBase):
    kind: Literal["oscillation"]
    amplitude: list[float] = Field(description="Sine amplitude per channel, channel units")
    freq_hz: list[Annotated[float, Field(ge=0.0)]] = Field(description="Sine frequency per channel, Hz")
    phase_rad: list[float] = Field(description="Phase at start_s per channel, rad")
    _params: ClassVar[tuple[str, ...]] = ("amplitude", "freq_hz", "phase_rad")


class ScaleFault(_FaultBase):
    kind: Literal["scale"]
    factor: list[float] = Field(description="Multiplier per channel (1 = no effect)")
    _params: ClassVar[tuple[str, ...]] = ("factor",)


class OutlierFault(_FaultBase):
    kind: Literal["outliers"]
    sigma: float = Field(gt=0.0, description="1 sigma of the channels, channel units (outlier = k sigma)")
    multiples: list[Annotated[float, Field(gt=0.0)]] = Field(
        min_length=1, description="Outlier sizes in sigmas, drawn uniformly per outlier (e.g. [3, 5, 8])"
    )
    fraction: float = Field(
        gt=0.0, le=1.0, description="Probability of an outlier per epoch or per channel (see per)"
    )
    per: Literal["epoch", "channel"] = Field(
        "epoch", description="'epoch': fraction of epochs carry per_epoch outliers; 'channel': of channels"
    )
    per_epoch: int = Field(1, ge=1, description="Channels hit at an outlier epoch (per = 'epoch')")


FaultSpec = Annotated[
    StepFault | RampFault | NoiseFault | RandomWalkFault | OscillationFault | ScaleFault | OutlierFault,
    Field(discriminator="kind"),
]
_FAULT_LIST = TypeAdapter(list[FaultSpec])


def parse_faults(data: list[dict]) -> list:
    """Validate a list of fault tables (raises pydantic.ValidationError naming the field)."""
    return _FAULT_LIST.validate_python(data)


class FaultSet:
    """The faults of one run, with their random states.

    Parameters
    ----------
    specs : list of FaultSpec (or dicts)
    rng : numpy.random.Generator
        Seeded; one child generator is spawned per fault.
    """

    def __init__(self, specs: list, rng: np.random.Generator):
        self.specs = [s if isinstance(s, BaseModel) else parse_faults([s])[0] for s in specs]
        self._rngs = rng.spawn(len(self.specs)) if self.specs else []
        # random-walk state per fault: (last time, values per channel)
        self._rw: dict[int, tuple[float, np.ndarray]] = {}
        # outlier hits per fault: rounded time -> channels hit (for ``active``)
        self._hits: dict[int, dict[float, list[str]]] = {}

    def for_sensor(self, sensor: str) -> list:
        return [s for s in self.specs if s.sensor == sensor]

    def apply(
        self, sensor: str, t_rel_s: float, values: dict[str, float], published=None
    ) -> dict[str, float]:
        """Return ``values`` (channel -> value) with the faults of ``sensor`` active at ``t_rel_s`` applied.

        Calls for one sensor must come in non-decreasing time (random walks advance with time).
        ``published``: the channels the sensor really publishes now (outlier candidates; default
        every channel of ``values``).
        """
        out = dict(values)
        for i, f in enumerate(self.specs):
            if f.sensor != sensor or not f.is_active(t_rel_s):
                continue
            if f.kind == "outliers":
                self._outliers(i, f, t_rel_s, out, values if published is None else published)
                continue
            missing = [c for c in f.channels if c not in out]
            if missing:
                raise KeyError(
                    f"fault {i} ({f.kind} on {sensor}) names channels {missing} the sensor does not have"
                )
            tau = t_rel_s - f.start_s
            if f.kind == "step":
                add = f.magnitude
            elif f.kind == "ramp":
                add = [r * tau for r in f.rate_per_s]
            elif f.kind == "noise":
                z = self._rngs[i].standard_normal(len(f.channels))
                add = [m + s * float(zj) for m, s, zj in zip(f.mean, f.std, z, strict=True)]
            elif f.kind == "random_walk":
                t_last, w = self._rw.get(i, (f.start_s, np.zeros(len(f.channels))))
                if t_rel_s < t_last:
                    raise ValueError(
                        f"fault {i}: random walk called backwards in time ({t_rel_s} < {t_last})"
                    )
                z = self._rngs[i].standard_normal(len(f.channels))
                w = w + np.asarray(f.sigma_per_sqrt_s) * math.sqrt(t_rel_s - t_last) * z
                self._rw[i] = (t_rel_s, w)
                add = w.tolist()
            elif f.kind == "oscillation":
                add = [
                    a * math.sin(2.0 * math.pi * fr * tau + ph)
                    for a, fr, ph in zip(f.amplitude, f.freq_hz, f.phase_rad, strict=True)
                ]
            else:  # scale
                for c, k in zip(f.channels, f.factor, strict=True):
                    out[c] = out[c] * k
                continue
            for c, a in zip(f.channels, add, strict=True):
                out[c] = out[c] + a
        return out

    def _outliers(self, i: int, f: OutlierFault, t_rel_s: float, out: dict[str, float], published) -> None:
        rng = self._rngs[i]
        cands = sorted(c for c in published if c in out and any(fnmatchcase(c, p) for p in f.channels))
        if f.per == "channel":
            pick = np.flatnonzero(rng.random(len(cands)) < f.fraction)
        else:
            if rng.random() >= f.fraction or not cands:
                return
            pick = rng.choice(len(cands), size=min(f.per_epoch, len(cands)), replace=False)
        if not len(pick):
            return
        hit = []
        for j in sorted(int(k) for k in pick):
            k_sigma = f.multiples[int(rng.integers(len(f.multiples)))]
            sign = 1.0 if rng.random() < 0.5 else -1.0
            out[cands[j]] = out[cands[j]] + sign * k_sigma * f.sigma
            hit.append(cands[j])
        self._hits.setdefault(i, {})[round(t_rel_s, 6)] = hit

    def active(self, t_rel_s: float) -> list[ActiveFault]:
        """Faults active at ``t_rel_s`` as wire models (for Truth messages). An outlier fault is
        listed only at the epochs it hit, with the channels it hit."""
        out = []
        for i, f in enumerate(self.specs):
            if not f.is_active(t_rel_s):
                continue
            if f.kind == "outliers":
                hit = self._hits.get(i, {}).get(round(t_rel_s, 6))
                if hit:
                    out.append(ActiveFault(sensor=f.sensor, kind=f.kind, channels=list(hit)))
                continue
            out.append(ActiveFault(sensor=f.sensor, kind=f.kind, channels=list(f.channels)))
        return out
