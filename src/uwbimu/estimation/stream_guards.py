"""Input guards of the streaming filter (:class:`uwbimu.estimation.streaming.Eskf`).

What a push may contain, how a refused sample is reported, and the consistency monitor that tells
:meth:`Eskf.state` whether the estimate can be trusted.  The policy, per case, is in the class docstring
of :class:`~uwbimu.estimation.streaming.Eskf` and in ``docs/estimator.md`` ("Streaming input guards").

The per-sample checks are plain-float comparisons (``push_imu`` runs at the IMU rate); the monitor
works on the measurement records the compiled loop writes, a slice of new rows at a time.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
from pydantic import BaseModel

from uwbimu.errors import ConfigError, StreamInputError, UsageError
from uwbimu.estimation.kernels import REC_NIS, REC_STATUS, UPD_OK
from uwbimu.estimation.options import EskfOptions
from uwbimu.io.yamlconfig import validate_model
from uwbimu.models.imu import ImuNoise

#: largest plausible specific force [m/s^2] (50 g: beyond the range of the IMUs the toolkit models)
MAX_ACC = 50.0 * 9.81
#: largest plausible body rate [rad/s] (about 2000 deg/s, the widest common gyro range)
MAX_GYRO = 35.0
#: slack [m] on the geometric bounds of a range and a TDoA (noise, lever arm, anchor survey error)
GEOMETRY_SLACK_M = 1.0


def check_options(opts: Any) -> EskfOptions:
    """The constructor's options validated as a configuration file is: a model changed after it was
    built (pydantic does not check assignments) or made with ``model_construct`` is validated again,
    and every number must be finite.  Raises :class:`ConfigError` naming the field."""
    if not isinstance(opts, EskfOptions):
        raise UsageError(f"Eskf: options must be an EskfOptions, got {type(opts).__name__}",
                         hint="build them with EskfOptions(...) or EskfOptions.from_yaml(path)")
    validate_model(opts.model_dump(), EskfOptions, source="Eskf(options=...)", what="estimator options")
    bad = _non_finite(opts, "")
    if bad is not None:
        name, value = bad
        raise ConfigError(f"Eskf(options=...): invalid estimator options (1 error(s))\n  field '{name}': "
                          f"must be a finite number, got {value!r}", hint=f"set {name} to a finite value")
    return opts


def _non_finite(model: BaseModel, prefix: str) -> Optional[tuple[str, float]]:
    for name in type(model).model_fields:
        v = getattr(model, name)
        vals = v if isinstance(v, (list, tuple)) else [v]
        for x in vals:
            if isinstance(x, BaseModel):
                bad = _non_finite(x, f"{prefix}{name}.")
                if bad is not None:
                    return bad
            elif isinstance(x, float) and not math.isfinite(x):
                return f"{prefix}{name}", x
    return None


def check_imu_noise(noise: Any) -> None:
    """The constructor's ``imu_noise``: an :class:`ImuNoise` whose densities are finite and >= 0."""
    if not isinstance(noise, ImuNoise):
        raise UsageError(f"Eskf: imu_noise must be an ImuNoise, got {type(noise).__name__}",
                         hint="use uwbimu.models.imu.imu_preset(name) or ImuNoise(...)")
    for name in type(noise).model_fields:
        v = getattr(noise, name)
        if isinstance(v, float):
            positive(f"imu_noise.{name}", v, zero=True)


def finite_number(name: str, value: Any) -> float:
    """A constructor argument that must be a finite number (any sign)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UsageError(f"Eskf: {name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise UsageError(f"Eskf: {name} must be finite, got {value!r}")
    return v


def positive(name: str, value: Any, *, allow_none: bool = True, zero: bool = False) -> Optional[float]:
    """A constructor argument that must be a finite number > 0 (``>= 0`` with ``zero``), or None."""
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UsageError(f"Eskf: {name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not zero):
        raise UsageError(f"Eskf: {name} must be a finite number {'>=' if zero else '>'} 0, got {value!r}",
                         hint=f"give {name} in SI units, or leave it out for the default")
    return v


def push_sigma(name: str, value: float) -> float:
    """A noise sd given to a push (``push_height(sigma=)``, ``push_zero_velocity(sigma=)``)."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise StreamInputError(f"Eskf: {name} must be a finite number > 0, got {value!r}", field=name,
                               reason="bad_sigma")
    return v


def as_floats(name: str, value: Any, width: Optional[int] = None) -> np.ndarray:
    """``value`` as a float array: ``(n,)`` (``width`` None) or ``(n, width)``; refused when it is not
    numeric or has another shape."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise StreamInputError(f"Eskf: {name} must hold numbers", field=name, reason="not_numeric") from None
    if width is None:
        if a.ndim > 1:
            raise StreamInputError(f"Eskf: {name} must be one-dimensional, got shape {a.shape}", field=name,
                                   reason="bad_shape")
        return a.reshape(-1)
    if a.ndim == 1 and a.shape[0] == width:
        return a.reshape(1, width)
    if a.ndim != 2 or a.shape[1] != width:
        raise StreamInputError(f"Eskf: {name} must have shape (n, {width}), got {a.shape}", field=name,
                               reason="bad_shape")
    return a


def same_length(what: str, **arrays: Any) -> int:
    """The common length of the arrays of one push (refused when they differ)."""
    lens = {k: len(v) for k, v in arrays.items()}
    if len(set(lens.values())) > 1:
        raise StreamInputError(f"Eskf.{what}: arguments of different lengths {lens}",
                               field=",".join(lens), reason="length_mismatch")
    return next(iter(lens.values()), 0)


class Rejections:
    """Refused samples as structured events: ``{"t", "kind": "input_rejected", "stream", "reason",
    "count", "t_last"}``.  A run of rejections of one stream and reason is one event (its ``count``
    grows) until another event comes between, so a stream of bad samples does not grow the event list
    without bound; ``counts`` holds the totals (reported again by ``finish``)."""

    def __init__(self, events: list, counts: dict[str, int]):
        self.events = events
        self.counts = counts
        self._open: dict[tuple[str, str], dict[str, Any]] = {}
        self._n_events = 0

    def add(self, stream: str, reason: str, t: float, n: int = 1, **fields) -> None:
        if n <= 0:
            return
        self.counts[reason] = self.counts.get(reason, 0) + int(n)
        t = float(t) if math.isfinite(t) else None
        ev = self._open.get((stream, reason))
        if ev is not None and len(self.events) == self._n_events and ev is self.events[-1]:
            ev["count"] += int(n)
            ev["t_last"] = t
            return
        if len(self.events) != self._n_events:
            self._open.clear()  # another event came between: start new runs
        ev = {"t": t, "kind": "input_rejected", "stream": stream, "reason": reason, "count": int(n),
              "t_last": t, **fields}
        self.events.append(ev)
        self._open[(stream, reason)] = ev
        self._n_events = len(self.events)


class NisMonitor:
    """Consistency of a filter pass from its normalised innovations (NIS) of UWB measurements.

    Over the last ``window`` processed ranges / TDoAs (gated out ones included), the pass is
    *inconsistent* from when more than half of them have a NIS above ``limit`` (chi-square with one
    degree of freedom: its median is 0.45; ``limit`` 9 is a 3-sigma innovation) until fewer than a
    quarter have: the covariance no longer covers the error (a clock fault, a wrong initialisation).  A burst of outliers on a minority of
    the anchors does not trip it.  The verdict is computed per measurement in index order, so it does
    not depend on how the data were chunked.
    """

    def __init__(self, window: int = 50, limit: float = 9.0):
        self.window, self.limit = int(window), float(limit)
        self.reset(0)

    def reset(self, j: int) -> None:
        self.j = int(j)  # next record row to look at
        self.hist = np.zeros(0, dtype=bool)  # the last window - 1 verdicts "NIS above limit"
        self.inconsistent = False
        self.since: Optional[float] = None

    def shift(self, m: int) -> None:
        """The record buffer dropped ``m`` rows from its front."""
        self.j = max(self.j - m, 0)

    def update(self, rec: np.ndarray, mb: np.ndarray, t: np.ndarray, j_end: int) -> list[dict[str, Any]]:
        """Look at record rows ``[self.j, j_end)``; the events of entering / leaving inconsistency."""
        j0 = self.j
        if j_end <= j0:
            return []
        self.j = j_end
        r = rec[j0:j_end]
        used = (r[:, REC_STATUS] == UPD_OK) & (mb[j0:j_end] >= -1) & np.isfinite(r[:, REC_NIS])
        if not used.any():
            return []
        high = r[used, REC_NIS] > self.limit
        tt = t[j0:j_end][used]
        seq = np.concatenate([self.hist, high])
        c = np.concatenate([[0], np.cumsum(seq)])
        n0 = len(self.hist)
        w = self.window
        idx = np.arange(n0, len(seq))
        lo = np.maximum(idx + 1 - w, 0)
        full = idx + 1 >= w
        frac = (c[idx + 1] - c[lo]) / w
        enter = full & (frac > 0.5)
        leave = frac < 0.25  # hysteresis: a pass that just came back within its sd is watched a while
        self.hist = seq[-(w - 1):] if w > 1 else seq[:0]
        events = []
        state = self.inconsistent
        i = 0
        while True:
            cand = np.flatnonzero((leave if state else enter)[i:])
            if not len(cand):
                break
            i += int(cand[0])
            state = not state
            ti = float(tt[i])
            if state:
                self.since = ti
                events.append({"t": ti, "kind": "inconsistent", "window": w, "limit": self.limit,
                               "fraction_above": float(frac[i])})
            else:
                events.append({"t": ti, "kind": "consistent_again", "since": self.since})
                self.since = None
        self.inconsistent = state
        return events
