"""A federated bank carried over a gap (issue 22): ``FederatedCore.carry_private``.

A member of the federated core keeps its private states (a DVL offset, ...) as a conditional on the
common ones; when a reset carries the common states over a gap (position on with the velocity,
every variance grown by what the gap may hide), the private marginal and its cross-covariance
with the common states must survive: nothing happened to a sensor's offset. Kept as a conditional
as it was, the offset would become as uncertain as the carried velocity.
"""

from __future__ import annotations

import numpy as np

from fednav.service.estimation.federated.core import FederatedCore, LinearBank
from fednav.service.estimation.federated.fault_tests import make_fault_test
from fednav.service.estimation.federated.sharing import get_strategy

C = 2  # common: position, velocity; private: the velocity sensor's offset


def _bank(steps: int = 200, seed: int = 5):
    """Two locals (position; velocity + offset) and an output-only master, fused every step with
    the EDOP sharing of the underwater family (the velocity local keeps a tiny share of the commons:
    its offset is known only relative to them)."""
    dt = 1.0
    Phi = np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    Q = np.diag([0.0, 1e-6, 1e-10])
    P0 = np.diag([100.0, 1.0, 0.25])
    bank = LinearBank(P0, FederatedCore.bank_size(2))
    core = FederatedCore(bank, 2, get_strategy("edop"), n_common=C)
    core.start()
    test = make_fault_test("none")
    rng = np.random.default_rng(seed)
    x = np.array([0.0, 1.0, 0.3])
    H0, R0 = np.array([[1.0, 0.0, 0.0]]), np.array([[4.0]])
    H1, R1 = np.array([[0.0, 1.0, 1.0]]), np.array([[1e-4]])
    for _ in range(steps):
        x = Phi @ x
        bank.predict(Phi, Q)
        core.update(0, H0 @ x + 2.0 * rng.standard_normal(1) - H0 @ bank.ref, H0, R0, test)
        core.update(1, H1 @ x + 0.01 * rng.standard_normal(1) - H1 @ bank.ref, H1, R1, test)
        core.fuse_and_reset()
    return core, bank


def _marginal(core: FederatedCore, P: np.ndarray, member: int) -> tuple[float, np.ndarray]:
    """(private variance, Cov(private, common)) as the member and the fused commons define them."""
    Pg = core.fused_covariance_of(P)
    Pcc, Pcp, Ppp = P[member, :C, :C], P[member, :C, C:], P[member, C:, C:]
    At = np.linalg.solve(Pcc, Pcp)
    return float((Ppp - Pcp.T @ At + At.T @ Pg @ At)[0, 0]), (At.T @ Pg)[0]


def test_a_carry_keeps_the_private_marginal_and_every_member_positive_definite():
    core, bank = _bank()
    P_old = bank.P.copy()
    var_old, cross_old = _marginal(core, P_old, 1)
    assert var_old < 0.01  # the offset is known (to < 0.1 m/s) through the velocity it was learnt with
    G = np.diag([0.0, 1.0])  # the gap hides 1 m/s of velocity
    P_new = P_old.copy()
    P_new[:, :C, :C] += G
    naive, _ = _marginal(core, P_new, 1)
    assert naive > 10 * var_old  # the conditional kept as it was: the offset as unknown as the velocity
    core.carry_private(P_old, P_new, np.eye(C), np.ones(C, dtype=bool))
    var_new, cross_new = _marginal(core, P_new, 1)
    assert abs(var_new - var_old) <= 1e-9 * max(1.0, var_old) + 1e-15, (var_old, var_new)
    np.testing.assert_allclose(cross_new, cross_old, rtol=1e-8, atol=1e-14)
    for m in range(P_new.shape[0]):
        assert np.linalg.eigvalsh(P_new[m]).min() > 0.0, m


def test_a_replaced_common_state_keeps_no_correlation():
    core, bank = _bank()
    P_old = bank.P.copy()
    P_new = P_old.copy()
    P_new[:, 1, :] = 0.0  # the velocity replaced outright (a reset from a reference)
    P_new[:, :, 1] = 0.0
    P_new[:, 1, 1] = 0.25
    var_old, _ = _marginal(core, P_old, 1)
    core.carry_private(P_old, P_new, np.eye(C), np.array([True, False]))
    var_new, cross_new = _marginal(core, P_new, 1)
    assert abs(cross_new[1]) < 1e-12
    assert abs(var_new - var_old) <= 1e-9 * max(1.0, var_old) + 1e-15
    assert np.linalg.eigvalsh(P_new[1]).min() > 0.0
