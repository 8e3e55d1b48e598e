"""ImuBatch: N IMU intervals in one binary payload, validated as arrays.

A 200 Hz IMU sent one JSON document per sample costs a publication, a parse and a pydantic object
per sample; a fleet of vehicles multiplies that. A batch carries N samples of one IMU in a fixed
little-endian layout (declared here and in docs/DESIGN.md "Wire contract"), published under the
same key as the per-sample JSON (``{prefix}/{vehicle}/sensor/imu/{id}``) with the Zenoh encoding
:data:`ENCODING`. The service tells the two apart by the payload's first bytes (:data:`MAGIC`; a
JSON document starts with ``{`` or whitespace), so a client may send either.

Layout, version 1 (all little-endian)::

    offset  size  field
    0       4     magic b"FNIB"
    4       2     version (uint16) = 1
    6       2     flags (uint16) = 0 (reserved; a batch with other flags is refused)
    8       4     count N (uint32), 1 <= N <= MAX_SAMPLES
    12      4     reserved (uint32) = 0
    16      64*N  N records of 8 float64: t, dt_s, dtheta_rad[3], dvel_mps[3]

Each record has exactly the meaning of one :class:`~service.messages.ImuSample` (t: end of the
interval in seconds of GPS time; increments in the body frame, right-forward-up). The payload
is exactly ``16 + 64 N`` bytes: a shorter (truncated) or longer one is refused whole
(``batch_truncated`` / ``batch_size``), so is a wrong magic, version or flags (``batch_header``)
or more than :data:`MAX_SAMPLES` samples (``batch_oversize``).

Validation of the records is vectorised and keeps every per-sample rule of the bad-input contract
(the same limits as ``ImuSample``): a record with a non-finite value is refused ``non_finite``, an
interval outside (0, MAX_DT_S] or a time outside [0, T_MAX_S] ``out_of_range``, increments implying
a rate or specific force above the plausibility limits ``absurd_value``. Only that record is lost;
the others go on. The time rules against the running time (duplicate, time backwards, overlap,
future, gaps, time jumps) are the engine's (:mod:`service.intake_rules`), applied per record.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from fednav.service.messages import MAX_DT_S, MAX_RATE_RPS, MAX_SPECIFIC_FORCE_MPS2, T_MAX_S

MAGIC = b"FNIB"
VERSION = 1
HEADER = struct.Struct("<4sHHII")
HEADER_BYTES = HEADER.size  # 16
RECORD_FIELDS = 8
RECORD_BYTES = 8 * RECORD_FIELDS  # 64
#: samples per batch at most (20 s of a 200 Hz IMU; the payload then is ~256 KiB)
MAX_SAMPLES = 4096
#: batches up to this many records are validated by a plain loop first (:func:`validate`)
SMALL_BATCH = 64
ENCODING = f"application/octet-stream;fednav.ImuBatch/{VERSION}"
_F8 = np.dtype("<f8")
#: columns of a decoded batch
T, DT, DTH, DV = 0, 1, slice(2, 5), slice(5, 8)


def batch_size_arg(text: str) -> int:
    """``--imu-batch N`` of the publishers: 1 (JSON per sample) .. MAX_SAMPLES."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= n <= MAX_SAMPLES:
        raise argparse.ArgumentTypeError(f"{n} samples: use 1 (JSON per sample) .. {MAX_SAMPLES}")
    return n


class BatchError(ValueError):
    """A batch refused whole; ``reason`` is the counted rejection reason."""

    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


def is_batch(payload: bytes | bytearray | memoryview) -> bool:
    """True when the payload is an ImuBatch (its magic), not a JSON document."""
    return payload[:4] == MAGIC  # (a slice of any of the three compares with bytes: no copy)


def encode(rows: np.ndarray) -> bytes:
    """Payload of an (N, 8) array of records (t, dt_s, dtheta_rad[3], dvel_mps[3])."""
    a = np.ascontiguousarray(rows, dtype="<f8")
    if a.ndim != 2 or a.shape[1] != RECORD_FIELDS or not 1 <= a.shape[0] <= MAX_SAMPLES:
        raise ValueError(f"an ImuBatch is 1..{MAX_SAMPLES} records of {RECORD_FIELDS} values, got {a.shape}")
    return HEADER.pack(MAGIC, VERSION, 0, a.shape[0], 0) + a.tobytes()


def encode_samples(samples) -> bytes:
    """Payload of a sequence of objects with ``t, dt_s, dtheta_rad, dvel_mps`` (ImuSample)."""
    return encode(np.array([(s.t, s.dt_s, *s.dtheta_rad, *s.dvel_mps) for s in samples], dtype=float))


def decode(payload: bytes | bytearray | memoryview) -> np.ndarray:
    """The (N, 8) float64 records of a payload; :class:`BatchError` when refused whole."""
    n_bytes = len(payload)
    if n_bytes < HEADER_BYTES:
        raise BatchError("batch_truncated", f"ImuBatch of {n_bytes} bytes is shorter than its header")
    magic, version, flags, count, _ = HEADER.unpack_from(payload, 0)
    if magic != MAGIC or version != VERSION or flags != 0:
        raise BatchError(
            "batch_header",
            f"ImuBatch header not understood (magic {magic!r}, version {version}, flags {flags})",
        )
    if not 1 <= count <= MAX_SAMPLES:
        raise BatchError("batch_oversize", f"ImuBatch declares {count} samples (1..{MAX_SAMPLES} allowed)")
    expected = HEADER_BYTES + RECORD_BYTES * count
    if n_bytes < expected:
        text = f"ImuBatch declares {count} samples but has {n_bytes} of {expected} bytes"
        raise BatchError("batch_truncated", text)
    if n_bytes > expected:
        text = f"ImuBatch declares {count} samples but has {n_bytes} bytes, not {expected}"
        raise BatchError("batch_size", text)
    # the records in place, by one constructor (frombuffer and reshape: two calls, ~2x the time in
    # a micro-benchmark)
    return np.ndarray((count, RECORD_FIELDS), _F8, payload, HEADER_BYTES)


def validate(rows: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Per-record checks of the bad-input contract, vectorised: (mask of usable records, counts of
    refused records by reason). The reasons and limits are those of ``ImuSample``'s validation.

    Every comparison with a NaN or an infinity is false, so a record that passes the range and
    plausibility tests is finite: the usual all-good batch costs one pass; the per-reason counts
    are computed only when some record fails.

    A batch of up to :data:`SMALL_BATCH` records (a sender's usual batch) is checked first in plain
    Python, with ImuSample's own arithmetic (``messages._norm``): at ten records the array checks'
    per-call overhead costs ~3x more than the loop. Only when a record fails there does the
    vectorised pass name and count the refusals."""
    n = len(rows)
    if n <= SMALL_BATCH and usual_records(rows) is not None:
        return np.ones(n, dtype=bool), {}
    with np.errstate(invalid="ignore", over="ignore"):
        t, dt = rows[:, T], rows[:, DT]
        rate = np.sqrt(np.einsum("ij,ij->i", rows[:, DTH], rows[:, DTH]))
        force = np.sqrt(np.einsum("ij,ij->i", rows[:, DV], rows[:, DV]))
        in_range = (dt > 0.0) & (dt <= MAX_DT_S) & (t >= 0.0) & (t <= T_MAX_S)
        plausible = in_range & (rate <= MAX_RATE_RPS * dt) & (force <= MAX_SPECIFIC_FORCE_MPS2 * dt)
    if plausible.all():
        return plausible, {}
    finite = np.isfinite(rows).all(axis=1)
    in_range &= finite
    plausible &= finite
    counts = {}
    for reason, n in (
        ("non_finite", int((~finite).sum())),
        ("out_of_range", int((finite & ~in_range).sum())),
        ("absurd_value", int((in_range & ~plausible).sum())),
    ):
        if n:
            counts[reason] = n
    return plausible, counts


def usual_records(rows: np.ndarray) -> list[list[float]] | None:
    """The records of a batch of up to :data:`SMALL_BATCH` as lists of floats when every one
    passes :func:`validate`'s rules (the usual batch), else None (then :func:`validate` names and
    counts the refusals). The small-batch check of :func:`validate`, whose floats the engine
    takes as they are: a batch's records are read into Python floats once, without validate's
    mask (``VehicleLoop._batch``)."""
    if len(rows) > SMALL_BATCH:
        return None
    records = rows.tolist()
    for t, dt, a0, a1, a2, v0, v1, v2 in records:
        if not (
            0.0 < dt <= MAX_DT_S
            and 0.0 <= t <= T_MAX_S
            and math.sqrt(a0 * a0 + a1 * a1 + a2 * a2) <= MAX_RATE_RPS * dt
            and math.sqrt(v0 * v0 + v1 * v1 + v2 * v2) <= MAX_SPECIFIC_FORCE_MPS2 * dt
        ):
            return None
    return records


class ImuRow:
    """One record of a batch with the attributes of an ImuSample (``t``, ``dt_s``,
    ``dtheta_rad``, ``dvel_mps``), for the consumers that take a sample object (transfer
    alignment nodes): no pydantic object, no second validation."""

    __slots__ = ("t", "dt_s", "dtheta_rad", "dvel_mps")

    def __init__(self, row) -> None:
        self.t = float(row[0])
        self.dt_s = float(row[1])
        self.dtheta_rad = (float(row[2]), float(row[3]), float(row[4]))
        self.dvel_mps = (float(row[5]), float(row[6]), float(row[7]))


__all__ = [
    "ENCODING",
    "MAGIC",
    "MAX_SAMPLES",
    "BatchError",
    "ImuRow",
    "decode",
    "encode",
    "encode_samples",
    "is_batch",
    "usual_records",
    "validate",
]
