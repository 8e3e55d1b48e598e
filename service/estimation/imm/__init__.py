"""Interacting multiple model bank (He, Nie, Wu 2011): mixing, per-model update, probabilities,
combined output (:mod:`.core`) with fault-model plug-ins (:mod:`.models`)."""
