"""Federated filtering: the core (local filters on one bank, master fusion, reset), the
information-sharing strategies and the fault-test plug-ins."""
