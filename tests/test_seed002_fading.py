"""Seed 002 fading (issue 25): the uncertainty the fading factor adds to the flexure angle moves
the lever arm's flexure part with it (dr = dr0 + M theta), so fading keeps the model's structure."""

from __future__ import annotations

import numpy as np

from fednav.service.estimation import transfer_alignment as ta
from fednav.service.estimation.adaptive import faded_covariance


def _bank(**kw) -> ta.TransferAlignmentBank:
    p = ta.TAParams(
        lever_arm_m=[[0.85, 0.15, 0.25], [2.0, 0.15, 0.28], [2.65, 0.15, 0.31]],
        flex_beta_rps=[1.0, 0.8, 1.2],
        flex_sigma_rad=np.radians(np.array([[1.0, 2.0, 0.5], [2.0, 4.0, 1.0], [3.0, 6.0, 1.5]]) / 60.0),
        arw_rad_psqrts=1e-5,
        vrw_mps_psqrts=5e-4,
        gyro_bias_rps=2.4e-7,
        accel_bias_mps2=1.5e-3,
        R0=np.full(9, 1e-6),
    )
    return ta.TransferAlignmentBank(p, mode="akf", **kw)


def _case(rng):
    A = rng.standard_normal((3, 27, 27))
    J = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(27)
    Qd = 1e-3 * np.eye(27)[None].repeat(3, 0)
    s = np.ones((3, 27))
    s[:, ta.FADING_STATES] = 1.0 + rng.uniform(0.0, 2.0, (3, int(ta.FADING_STATES.sum())))
    s[1] = 1.0  # member 1 did not trigger
    return J, Qd, s


def test_fading_moves_the_lever_arm_with_the_flexure():
    rng = np.random.default_rng(5)
    bank = _bank()
    J, Qd, s = _case(rng)
    P = bank._faded(J, s, Qd)
    added = P - J - Qd
    M = bank.p.M
    for b in (0, 2):
        # the added perturbation d satisfies d_dr = M d_theta: the lever arm follows the flexure
        np.testing.assert_allclose(added[b][ta.DR, :], M[b] @ added[b][ta.TH, :], atol=1e-12)
        # and it is the congruence T J T' (positive semi-definite): fading only adds uncertainty
        assert np.linalg.eigvalsh(added[b]).min() > -1e-9
        # the other states get the plain "added" form's inflation
        plain = faded_covariance(J, s, Qd, "added")
        keep = np.r_[0:15, 18:21, 24:27]
        np.testing.assert_allclose(P[b][np.ix_(keep, keep)], plain[b][np.ix_(keep, keep)], atol=1e-12)
    # a member whose factors are all 1 is untouched, bit for bit
    np.testing.assert_array_equal(P[1], faded_covariance(J, s, Qd, "added")[1])


def test_no_flexure_fading_or_option_off_is_the_plain_added_form():
    rng = np.random.default_rng(6)
    J, Qd, s = _case(rng)
    np.testing.assert_array_equal(
        _bank(lever_follows_flexure=False)._faded(J, s, Qd), faded_covariance(J, s, Qd, "added")
    )
    s[:, ta.TH] = 1.0  # theta not faded: nothing to carry over
    np.testing.assert_array_equal(_bank()._faded(J, s, Qd), faded_covariance(J, s, Qd, "added"))
    np.testing.assert_array_equal(
        _bank(fading_form="scaled")._faded(J, s, Qd), faded_covariance(J, s, Qd, "scaled")
    )
