"""The linear baseline's response to the same load step (seed section 2).

"The main idea is to compare linear system as reference with a response of a
nonlinear real driveline in the range of natural frequencies" (seed, section
1).  The baseline is the mill file's driveline with every gap closed; being
linear in the load (the speed loop stays within its torque limit), its
response to a raised-cosine step of height ``S`` and rise time ``r`` is ``S``
times its unit response.  :class:`LinearReference` simulates unit responses on
a grid of rise times once per sample rate and keeps them; the rise time of a
measured step is the grid value whose unit response best matches the measured
edge (:meth:`LinearReference.fit_rise`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..description import Mill
from ..model.dynamics import ModelOptions
from ..model.linear import (LinearModes, damping_matrix, mass_matrix, natural_modes,
                           stiffness_matrix)
from ..model.scenario import Bar, Scenario, nominal_torque
from ..model.simulate import simulate
from .transients import Signal, half_crossing, static_shares

__all__ = ["UnitResponse", "LinearReference", "DEFAULT_RISE_GRID_S", "closed_loop_modes"]

#: rise times of the unit responses, s (10-40 ms is typical of real bites)
DEFAULT_RISE_GRID_S: tuple[float, ...] = tuple(np.round(np.arange(0.004, 0.0641, 0.004), 4))


def closed_loop_modes(mill: Mill) -> tuple[np.ndarray, np.ndarray]:
    """Frequencies and damping of the baseline with its speed loop closed.

    ``ident frequencies`` (and the seed's 12 ... 81 Hz) are the free-free modes
    with the speed loop open; a load-step transient rings at the closed-loop
    poles of ``M theta'' + C theta' + K theta = e_m (-kp omega_m + ki z)``,
    ``z' = -omega_m`` -- on the shipped stand the 12 and 20 Hz modes move to
    11.3 and 18.6 Hz with damping ratios 0.31 and 0.11 (the motor's loop damps
    them).  Each free-free mode is paired with the nearest oscillatory closed-loop
    pole (greedy, in order of frequency).

    Returns
    -------
    frequencies_hz : ndarray, shape (n_modes,)
        Damped frequencies of the closed-loop poles, Hz, in the order of
        :func:`ident.model.linear.natural_modes`.
    damping : ndarray, shape (n_modes,)
        Their damping ratios.
    """
    M = mass_matrix(mill)
    K = stiffness_matrix(mill)
    C = damping_matrix(mill)
    n = M.shape[0]
    im = mill.mass_index(mill.motor.mass)
    Minv = np.linalg.inv(M)
    A = np.zeros((2 * n + 1, 2 * n + 1))
    A[:n, n:2 * n] = np.eye(n)
    A[n:2 * n, :n] = -Minv @ K
    A[n:2 * n, n:2 * n] = -Minv @ C
    A[n + im, n + im] -= mill.motor.kp / M[im, im]
    A[n + im, 2 * n] += mill.motor.ki / M[im, im]
    A[2 * n, n + im] = -1.0
    ev = np.linalg.eigvals(A)
    osc = ev[ev.imag > 1e-6]
    f_cl = osc.imag / (2 * np.pi)
    z_cl = -osc.real / np.abs(osc)
    f_ol = natural_modes(mill).frequencies_hz
    free = list(range(len(osc)))
    freqs, zetas = [], []
    for f in f_ol:
        if not free:
            freqs.append(float(f))
            zetas.append(0.0)
            continue
        j = min(free, key=lambda i: abs(f_cl[i] - f))
        free.remove(j)
        freqs.append(float(f_cl[j]))
        zetas.append(float(z_cl[j]))
    return np.array(freqs), np.array(zetas)


@dataclass(frozen=True)
class UnitResponse:
    """Reduced element torques after a unit step of the total load.

    Attributes
    ----------
    rise_s : float
        Rise time of the raised-cosine step, s.
    rate_hz : float
    tau : ndarray, shape (n,)
        Time relative to the half-height instant of the summed torque of
        ``near`` elements, s.
    torques : dict of str to ndarray
        Per element, reduced torque per N*m of total load step (0 before, the
        element's static share long after).
    near : tuple of str
        The elements whose summed torque defines the half-height instant.
    """

    rise_s: float
    rate_hz: float
    tau: np.ndarray
    torques: dict[str, np.ndarray]
    near: tuple[str, ...]

    def at(self, element_id: str, tau: np.ndarray) -> np.ndarray:
        """Unit response of an element at times ``tau`` (s from the half-height)."""
        return np.interp(tau, self.tau, self.torques[element_id], left=0.0,
                         right=self.torques[element_id][-1])


class LinearReference:
    """Unit step responses of the linear baseline of one mill, kept once computed.

    Parameters
    ----------
    mill : Mill
    rise_grid_s : tuple of float
        Rise times to simulate, s.
    duration_s : float
        Length of each response after the step, s.

    Notes
    -----
    The cache lives in the instance (no global state); pass one instance to
    every feature extraction of a mill.  It pickles (for joblib workers) with
    the responses computed so far.
    """

    def __init__(self, mill: Mill, *, rise_grid_s: tuple[float, ...] = DEFAULT_RISE_GRID_S,
                 duration_s: float = 4.0) -> None:
        self.mill = mill
        self.rise_grid_s = tuple(float(r) for r in rise_grid_s)
        self.duration_s = float(duration_s)
        self._cache: dict[tuple[float, float, tuple[str, ...]], UnitResponse] = {}
        self._modes: LinearModes | None = None
        self._poles: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def modes(self) -> LinearModes:
        """Natural frequencies of the baseline (gaps closed, speed loop open): the labels."""
        if self._modes is None:
            self._modes = natural_modes(self.mill)
        return self._modes

    @property
    def poles(self) -> tuple[np.ndarray, np.ndarray]:
        """Closed-loop frequencies (Hz) and damping ratios the transients ring at."""
        if self._poles is None:
            self._poles = closed_loop_modes(self.mill)
        return self._poles

    def response(self, rise_s: float, rate_hz: float, near: tuple[str, ...]) -> UnitResponse:
        """Unit response for a rise time on the grid (nearest grid value)."""
        r = min(self.rise_grid_s, key=lambda g: abs(g - rise_s))
        key = (r, float(rate_hz), tuple(near))
        if key not in self._cache:
            self._cache[key] = self._simulate(r, float(rate_hz), tuple(near))
        return self._cache[key]

    def warm(self, rate_hz: float, near: tuple[str, ...]) -> "LinearReference":
        """Compute every grid rise time's unit response now (before pickling to workers).

        Returns
        -------
        LinearReference
            ``self``.
        """
        for r in self.rise_grid_s:
            self.response(r, rate_hz, near)
        return self

    def _simulate(self, rise_s: float, rate_hz: float, near: tuple[str, ...]) -> UnitResponse:
        mill = self.mill
        S = nominal_torque(mill)
        lead = 0.3
        dur = lead + self.duration_s + 0.2
        sc = Scenario(duration=dur, bars=(Bar(t_bite=lead, t_release=dur + 10.0,
                                              static_torque=S, rise_time=rise_s),))
        params = {}
        for e in mill.elements:
            params[f"{e.id}.gap"] = 0.0
            params[f"{e.id}.gap_open"] = 0.0
        res = simulate(mill, sc, options=ModelOptions(bearings=False), params=params,
                       rate_hz=rate_hz)
        out = res.outputs
        torques = {e.id: out[f"tau:{e.id}"].to_numpy() / S for e in mill.elements}
        ref = sum(torques[e] for e in near)
        share = sum(static_shares(mill)[e] for e in near)
        sig = Signal("ref", "ref", 0.0, rate_hz, ref)
        th = half_crossing(sig, lead + 0.5 * rise_s, 0.5 * share, True, span=0.05)
        if th is None:  # pragma: no cover - a unit step always crosses
            th = lead + 0.5 * rise_s
        tau = res.time - th
        return UnitResponse(rise_s=rise_s, rate_hz=rate_hz, tau=tau, torques=torques, near=near)

    def fit_rise(self, ref: Signal, t_step: float, pre: float, step: float, share: float,
                 near: tuple[str, ...], *, span_s: float = 0.04, max_shift_s: float = 0.005,
                 background: Callable[[np.ndarray], np.ndarray] | None = None
                 ) -> tuple[UnitResponse, float]:
        """The grid rise time and time shift whose unit response best matches a measured edge.

        Parameters
        ----------
        ref : Signal
            Summed torque of the ``near`` channels, reduced, N*m.
        t_step : float
            Its half-height instant, s.
        pre : float
            Its level before the step, N*m.
        step : float
            Total load step, N*m (the ``near`` channels see ``share`` of it).
        share : float
            Static share of the ``near`` elements.
        near : tuple of str
        span_s : float
            Half-width of the compared window around ``t_step``, s.
        max_shift_s : float
            The baseline's step may sit up to this far (s, in steps of a quarter
            sample) from ``t_step``: leftover ringing of earlier steps moves the
            measured half-height instant.
        background : callable, optional
            ``background(t)``: the baseline's leftover response to earlier
            steps in ``ref`` at absolute times ``t`` (N*m, zero before this
            step's pre window), subtracted before matching.

        Returns
        -------
        unit : UnitResponse
        shift_s : float
            Where the baseline's half-height instant sits relative to ``t_step``, s.
        """
        tau = np.arange(-span_s, span_s, 1.0 / ref.rate_hz)
        meas = ref.at(t_step + tau) - pre
        if background is not None:
            meas = meas - background(t_step + tau)
        meas = meas / step
        dt = 0.25 / ref.rate_hz
        shifts = np.arange(-max_shift_s, max_shift_s + 0.5 * dt, dt) if max_shift_s > 0 \
            else np.zeros(1)
        grid = (tau[None, :] - shifts[:, None]).ravel()
        best, best_shift, best_err = None, 0.0, np.inf
        for r in self.rise_grid_s:
            u = self.response(r, ref.rate_hz, near)
            model = sum(u.at(e, grid) for e in near).reshape(shifts.size, tau.size)
            # the step's height is free here: levels read from medians of ringing
            # signals are off by a percent, which would bias the rise time
            mm = np.einsum("ij,ij->i", model, model)
            a = np.where(mm > 0, model @ meas / np.where(mm > 0, mm, 1.0), 1.0)
            err = np.sum((meas[None, :] - a[:, None] * model) ** 2, axis=1)
            i = int(np.argmin(err))
            if err[i] < best_err:
                best, best_shift, best_err = u, float(shifts[i]), float(err[i])
        return best, best_shift  # type: ignore[return-value]  # the grid is never empty
