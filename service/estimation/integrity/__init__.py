"""Integrity monitoring: the MHSS bank (members and cross-covariances, separation tests,
exclusion search) and the monitor around it (alert limits, residual windows, exclusion memory)."""
