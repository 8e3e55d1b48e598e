"""An INS whose filter bank is an MHSS bank (main + sub + sub-sub filters with cross blocks).

:class:`MhssInsBank` is an :class:`~service.estimation.ins_filter.InsFilterBank` whose members
(``x``, ``P``) live in an :class:`~service.estimation.integrity.mhss.MhssBank`, so the base class's
closed-loop feedback shifts every member (and private-state references, e.g. the receiver clock);
its time update predicts members and cross-covariances in one call.
"""

from __future__ import annotations

import numpy as np

from fednav.service.estimation.ins_filter import InsFilterBank
from fednav.service.estimation.integrity.mhss import MhssBank
from fednav.service.estimation.measurements.base import PrivateStates
from fednav.service.ins import error_model as em
from fednav.service.ins.mechanisation import NavState


class MhssInsBank(InsFilterBank):
    def __init__(
        self,
        nav: NavState,
        P0: np.ndarray,
        noise: em.ImuNoise,
        major_interval_s: float = 0.1,
        private: tuple[PrivateStates, ...] = (),
        depth: int = 2,
    ):
        P0 = np.asarray(P0, dtype=float)
        self.mhss = MhssBank.initial(np.zeros(P0.shape[-1]), P0, (), depth)
        super().__init__(nav, P0, noise, bank_size=1, major_interval_s=major_interval_s, private=private)

    # the members live in the MHSS bank (the base class assigns x/P once in __init__: ignored)
    @property
    def x(self) -> np.ndarray:
        return self.mhss.x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        if np.any(value):
            raise ValueError("MhssInsBank members are set through the MHSS bank")

    @property
    def P(self) -> np.ndarray:
        return self.mhss.P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        pass

    @property
    def B(self) -> int:
        return self.mhss.B

    @B.setter
    def B(self, value: int) -> None:
        pass

    def predict_members(self, Phi: np.ndarray, Qd: np.ndarray) -> None:
        # one batched prediction of members and cross-covariances (full Q for every block)
        self.mhss.predict(Phi, Qd)


__all__ = ["MhssInsBank"]
