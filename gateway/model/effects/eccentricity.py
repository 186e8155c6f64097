"""``eccentricity``: a pulley off its axis adds a force periodic in cable travel
(docs/physics.md sec. 4).

The sensor reads ``+ a sin(x / r + phi)`` with ``x`` the cable length where it is known
(the soft PLC and the gateway: the setpoint length, so the phase is a property of the
pulley, not of the start of a run) and the travel since the first sample where it is not
(a recording without lengths: such a phase converts with ``phi_L = phi - L_0 / r``,
:func:`phase_at_length`, ``L_0`` the first sample's length). The fit varies
``(a cos phi, a sin phi, 1 / r)`` (amplitude and phase linear); the wave number's start
comes from a periodogram of the residual in cable travel (:func:`kappas`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from numba import njit

from gateway.model.effects.base import (
    INF,
    Effect,
    FitData,
    ModelFile,
    NominalChain,
    Online,
    Param,
    Sample,
    Series,
    Spec,
    Values,
)


@njit(cache=True)
def inverse_step(p, y, v, v_prev, dt, length):
    """Per cycle: ``y -= a sin(L / r + phi)``, ``L`` the setpoint length."""
    for i in range(y.size):
        if p[0, i] != 0.0:
            y[i] -= p[0, i] * math.sin(length[i] / p[1, i] + p[2, i])


def phase_at_length(phi_rad: float, r_m: float, length0_m: float) -> float:
    """Phase for ``x`` = cable length, from a phase fitted with ``x`` = travel since a
    sample whose length was ``length0_m``: ``a sin((L - L0)/r + phi) = a sin(L/r + phi')``.
    Wrapped to (-pi, pi]."""
    phi = phi_rad - length0_m / r_m
    return math.atan2(math.sin(phi), math.cos(phi))


KAPPA_BATCH = 16
"""Wave numbers per batch of the periodogram: six (20000, 16) float64 temporaries, 15 MB."""


def kappas(
    d: FitData, resid: np.ndarray, mask: np.ndarray, r_nom: float, top: int = 3
) -> list[float]:
    """Wave numbers ``1/r`` (rad/m) where the residual is most periodic in cable travel.

    A least-squares periodogram of ``resid`` against the displacement ``x`` on a grid of
    wave numbers from 2 turns over the travelled span up to 1/(2 mm), on at most 20000
    training samples; ``1/r_nom`` (the model's pulley radius) is always among them.
    """
    idx = np.nonzero(mask)[0]
    if idx.size > 20000:
        idx = idx[:: math.ceil(idx.size / 20000)]
    x, r = d.x[idx], resid[idx] - resid[idx].mean()
    span = float(np.ptp(d.x)) if d.x.size else 0.0
    if span <= 0:
        return [1.0 / r_nom]
    k_lo, k_hi = 4 * math.pi / span, 500.0
    if k_lo >= k_hi:
        return [1.0 / r_nom]
    n_grid = int(min(3000, max(200, (k_hi - k_lo) * span / (0.5 * math.pi))))
    grid = np.linspace(k_lo, k_hi, n_grid)
    power = np.empty(n_grid)
    for lo in range(0, n_grid, KAPPA_BATCH):
        kk = grid[lo : lo + KAPPA_BATCH]
        ph = np.outer(x, kk)
        s, c = np.sin(ph), np.cos(ph)
        ss, cc, sc = (s * s).sum(0), (c * c).sum(0), (s * c).sum(0)
        rs, rc = r @ s, r @ c
        det = np.maximum(ss * cc - sc**2, 1e-300)
        power[lo : lo + KAPPA_BATCH] = (cc * rs**2 - 2 * sc * rs * rc + ss * rc**2) / det
    order = np.argsort(power)[::-1]
    chosen: list[float] = []
    for j in order:
        if all(abs(grid[j] - c) > 2 * (grid[1] - grid[0]) for c in chosen):
            chosen.append(float(grid[j]))
        if len(chosen) >= top:
            break
    return [*chosen, 1.0 / r_nom]


class _Stepper:
    def __init__(self, a: np.ndarray, r: np.ndarray, phi: np.ndarray) -> None:
        self.a, self.r, self.phi = a, r, phi

    def step(self, s: Sample, y: np.ndarray) -> np.ndarray:
        return y + self.a * np.sin(s.x / self.r + self.phi)


class Eccentricity(Effect):
    name = "eccentricity"
    stage = "path"
    order = 20
    params = (
        Param("a_n", "N", 0.0, step=0.1, doc="amplitude"),
        Param(
            "r_m",
            "m",
            float("nan"),
            low=0.0,
            low_open=True,
            step=1e-3,
            nominal="pulley_radius_m",
            doc="radius of the pulley (travel per radian)",
        ),
        Param("phi_rad", "rad", 0.0, step=0.1, doc="phase at x = 0"),
    )
    physics = "+ a sin(x / r + phi), x the cable length"
    online = Online(True, "x the setpoint length")
    online_kernel = inverse_step
    group = "periodic"
    look = "the residual is periodic in cable travel (plot residual against x)"
    plot = "x"
    separate = "travel over several turns of the pulley"
    example = {"a_n": 2.0, "r_m": 0.012, "phi_rad": 0.7}

    def forward(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y + p["a_n"] * np.sin(s.x / p["r_m"] + p["phi_rad"])

    def inverse(self, s: Series, y: np.ndarray, p: Values) -> np.ndarray:
        return y - p["a_n"] * np.sin(s.x / p["r_m"] + p["phi_rad"])

    def stepper(self, p: Values, cables: int, period_s: float) -> _Stepper:
        def arr(name: str) -> np.ndarray:
            return np.broadcast_to(np.asarray(p[name], dtype=float), (cables,)).copy()

        return _Stepper(arr("a_n"), arr("r_m"), arr("phi_rad"))

    def present(self, values: Values, nom: NominalChain) -> np.ndarray:
        """Where the amplitude is not zero (radius and phase mean nothing without it)."""
        return np.asarray(values["a_n"], dtype=float) != 0.0

    def internal(self, values: Mapping[str, float]) -> np.ndarray:
        a, phi = float(values["a_n"]), float(values["phi_rad"])
        return np.array([a * math.cos(phi), a * math.sin(phi), 1.0 / float(values["r_m"])])

    def report(self, theta: np.ndarray) -> dict[str, float]:
        p = [float(v) for v in theta]
        return {"a_n": math.hypot(p[0], p[1]), "r_m": 1.0 / p[2], "phi_rad": math.atan2(p[1], p[0])}

    def report_stderr(self, theta: np.ndarray, se: np.ndarray) -> dict[str, float]:
        p, s = [float(v) for v in theta], [float(v) for v in se]
        amp = max(math.hypot(p[0], p[1]), 1e-300)
        return {
            "a_n": math.hypot(p[0] * s[0], p[1] * s[1]) / amp,
            "r_m": s[2] / p[2] ** 2,
            "phi_rad": math.hypot(p[1] * s[0], p[0] * s[1]) / amp**2,
        }

    def significance(self, theta: np.ndarray, se: np.ndarray, neutral: np.ndarray) -> float:
        """The amplitude over its standard error (the phase means nothing without it)."""
        amp = math.hypot(theta[0], theta[1])
        se_amp = math.hypot(theta[0] * se[0], theta[1] * se[1]) / max(amp, 1e-300)
        return amp / se_amp if se_amp > 0 else 0.0

    def applicable(self, d: FitData, nom: NominalChain) -> bool:
        """At least half a turn of the nominal pulley of travel (else it is an offset)."""
        span = float(np.ptp(d.x)) if d.x.size else 0.0
        return span >= math.pi * nom.pulley_radius_m

    def spec(self, d: FitData, nom: NominalChain, resid: np.ndarray, mask: np.ndarray) -> Spec:
        kap = kappas(d, resid, mask, nom.pulley_radius_m)
        span = max(float(np.ptp(d.x)), 1e-6)
        return Spec(
            np.array([0.0, 0.0, kap[-1]]),
            np.array([-INF, -INF, 2 * math.pi / span]),
            np.array([INF, INF, 1e3]),
            (0, 1),
            np.array([0.1, 0.1, 0.01]),
            tuple(np.array([0.0, 0.0, k]) for k in kap),
        )

    def from_fit(self, values: Values, ctx: ModelFile) -> None:
        """A phase fitted against the travel since the first sample -> against the cable
        length, where the recording has lengths."""
        if ctx.length0 is None:
            return
        ph, r = values["phi_rad"], values["r_m"]
        values["phi_rad"] = np.array(
            [
                phase_at_length(float(ph[i]), float(r[i]), float(ctx.length0[i]))
                for i in range(ph.size)
            ]
        )


EFFECT = Eccentricity()
