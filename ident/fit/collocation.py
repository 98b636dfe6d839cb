"""Direct collocation of the fit (the design's method), solved by IPOPT.

Every window's trajectory is piecewise polynomial: finite elements of
``elements_per_sample`` per measured sample, each a Radau IIA polynomial of
``degree`` through its start and ``degree`` collocation points, the dynamics
enforced at the collocation points.  Decision variables: the shared parameters,
per window the load ramp and the initial state, and the collocation states.
Measured torques are compared with the outputs at the sample instants, the
states there interpolated by the element's polynomials.

Formulation (exactly the Radau IIA scheme, smaller)
---------------------------------------------------
The driveline is second order, ``theta' = omega``, ``J omega' = F``, and the
speed loop's integral is ``z = z0 - theta_motor`` (``z' = -omega_motor``,
motor angle 0 at the window start).  Substituting the kinematic collocation
equations, ``omega`` at a collocation point *is* the derivative of the
``theta`` polynomial there, so per element only the angles at the collocation
points (``n`` each) and the speed at the element's end (``n``, tied to the
derivative by ``n`` equations) are variables; ``z`` is no variable at all.
That is 4n variables and equations per element instead of 3(2n+1): the KKT
blocks MUMPS factorises shrink, and with them the time per iteration.
States added by effects are collocated as ordinary first-order states.

Speed (``benchmarks/bench_fit.py`` measures it)
----------------------------------------------
* One block function (SX) covers a few samples and their elements; it is
  ``map``-ped over every block of every window.  Its gradient, Jacobian and
  Lagrangian Hessian are derived once per block symbolically and assembled
  into the NLP's sparse matrices by constant 0/1 maps (IPOPT's ``grad_f``,
  ``jac_g`` and ``hess_lag`` callbacks): building takes seconds and does not
  grow faster than the number of blocks.  (CasADi's own Hessian of the whole
  MX graph took 13 s for one 0.6 s window and 390 s for four.)
* Data, channel weights and all scales are NLP *parameters*: one built NLP
  serves every set of windows of the same lengths (cached in the strategy
  object), every continuation stage (the smoothing width is a parameter),
  every start and every profile-likelihood point.
* Continuation on the smoothing width warm-starts primal and dual variables.
* IPOPT with MUMPS, exact Hessian, ``mumps_permuting_scaling = 0`` and
  ``mumps_scaling = 0`` (with MUMPS' default scaling the first factorisation
  of these KKT systems ran out of memory).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from fractions import Fraction
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np
import scipy.sparse as sps

from ..errors import FitError
from ..model.dynamics import Family
from .problem import OUT_OF_TIME, Estimate, Problem, SolveInfo, StageInfo

__all__ = ["Collocation", "CollocationNLP", "simulate_estimate", "element_shape", "stationary",
           "STATIONARY"]


def _lagrange(tau_root: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Derivative matrix ``C[j, r] = dL_j/dtau(tau_r)`` and the Lagrange polynomials."""
    d1 = len(tau_root)
    polys = []
    C = np.zeros((d1, d1))
    for j in range(d1):
        p = np.poly1d([1.0])
        for r in range(d1):
            if r != j:
                p *= np.poly1d([1.0, -tau_root[r]]) / (tau_root[j] - tau_root[r])
        polys.append(p)
        dp = np.polyder(p)
        for r in range(d1):
            C[j, r] = dp(tau_root[r])
    return C, tuple(polys)


@dataclass(frozen=True, eq=False)
class CollocationNLP:
    """One built NLP (reused across data of the same structure)."""

    cold: Any
    warm: Any
    n_blocks: tuple[int, ...]
    samples_per_block: int
    elements_per_block: int
    degree: int
    tau_root: np.ndarray
    layout: dict
    n_x: int
    n_g: int
    build_seconds: float
    rjac: Any
    gjac: Any
    resid: Any
    samples: Any
    lengths: tuple[int, ...]
    definition: dict = field(default_factory=dict, repr=False)
    options: dict = field(default_factory=dict, repr=False)
    _solvers: dict = field(default_factory=dict, repr=False)

    def solver(self, *, warm: bool, tol: float | None = None,
               max_iter: int | None = None, max_cpu_s: float | None = None) -> Any:
        """The IPOPT instance (cold or warm start; ``tol``, ``max_iter`` and ``max_cpu_s``
        override the strategy)."""
        if tol is None and max_iter is None and max_cpu_s is None:
            return self.warm if warm else self.cold
        key = (warm, None if tol is None else float(tol), max_iter,
               None if max_cpu_s is None else float(max_cpu_s))
        got = self._solvers.get(key)
        if got is None:
            opts = dict(self.options)
            if warm:
                opts.update(_warm_options())
            if tol is not None:
                opts.update({"ipopt.tol": float(tol), "ipopt.acceptable_tol": 100.0 * float(tol),
                             "ipopt.acceptable_iter": 5})
            if max_iter is not None:
                opts["ipopt.max_iter"] = int(max_iter)
            if max_cpu_s is not None:
                opts["ipopt.max_cpu_time"] = float(max_cpu_s)
            got = ca.nlpsol(f"ident_coll_{'warm' if warm else 'cold'}_loose", "ipopt",
                            self.definition, opts)
            self._solvers[key] = got
        return got


@dataclass(frozen=True)
class Collocation:
    """Direct collocation strategy for :func:`ident.fit.fit_gaps`.

    Parameters
    ----------
    degree : int
        Radau collocation polynomial degree.
    elements_per_sample : float or None
        Finite elements per measured sample, a ratio of small integers (1/8,
        1/3, 1/2, 1, 2, ...).  None (the default): from the physics, the
        longest element that resolves the mill's highest natural frequency
        ``f_max`` (:func:`element_shape`: ``2 pi f_max h <= max_phase``), so
        that the discretisation is no model error at any recorded rate.
    max_phase : float
        Phase of the highest natural frequency over one element, rad, when
        ``elements_per_sample`` is None.  A degree-3 polynomial through the
        Radau points misses a sine by 0.08 % of its amplitude at 1 rad per
        element, 0.4 % at 1.5, 1.2 % at 2 and 5.5 % at 3.  The fixed 1/8 it
        replaces put cold-s5's 138 Hz mode at 3.5 rad per element on 2 kHz
        recordings: on an independent plant recording
        (``validation.plantsim``, seed 1000) with the plant's nuisances
        removed, the motor coupling's transient-band residual was 7.3 times
        the noise and the gaps 11 urad off; at 1.7 rad, 1.2 times and 5 urad.
    widths : tuple of float
        Continuation on the g1 smoothing width, rad, largest first; the last
        is the width of the reported model.  Ignored by g2/g3/g4.
    horizons : tuple of float
        Continuation on the fitted horizon first (at the first width): stages
        that weigh only samples up to this many seconds after each window's
        step, before the whole windows.  A release's rattle makes the cost
        rugged in the gaps; its first swings alone are not.
    tol : float
        IPOPT ``tol`` (the NLP is scaled by hand: states and parameters O(1),
        residuals in channel standard deviations).
    max_iter : int
        IPOPT iterations per stage.
    stage_tol : float or None
        IPOPT ``tol`` of every stage but the last (a continuation stage only
        has to bring the next one near its solution); None: ``tol`` throughout.
    settle : tuple of float
        Widths of the settling stages :func:`ident.fit.fit_gaps` runs before
        the fit proper: every shared parameter held at the start, only the
        windows' loads and initial states free.  Starting gaps are often wrong
        by millimetres; freeing everything at once lets the gaps explain wrong
        initial positions inside the gaps and ends in a local minimum (on a
        bite and a release of the shipped stand: C57 at 16 mrad instead of 5).
        Empty: no settling.
    horizon_width : {"first", "last"}
        Horizon continuation at the first width (then the widths on whole
        windows) or the widths on the first horizon, then the horizons at
        the last width.
    compile : bool
        Generate C for the block functions and compile them (cached on disk,
        ``ident.model.integrate.cache_dir``): the NLP callbacks run several
        times faster; falls back to CasADi's virtual machine without a compiler.
    ipopt : mapping
        Extra IPOPT options (override the defaults).
    width_warm : {"primal", "duals"}
        What a stage at a new smoothing width starts from: the last stage's
        primal point with fresh multipliers ("primal", the default), or its
        multipliers too ("duals").  Measured on a bite and a release of 2
        bars (seed 21 of ``tests/test_fit.py``): with the old multipliers the
        1e-4 rad stage met a dual infeasibility of 1e14, IPOPT regularised
        the Hessian by up to 1e13 and refactorised about 20 times per
        iteration: 336 s for 82 iterations; fresh multipliers, 15 s for 79
        iterations, to a lower cost.
    stage_max_iter : int or None
        IPOPT iterations of every stage but the last (None: ``max_iter``).
    max_cpu_s : float
        CPU seconds of one IPOPT call (``max_cpu_time``): a stage that takes
        longer stops with ``Maximum_CpuTime_Exceeded``, is not converged, and
        the fit says so.  A 4-window stage takes 1-60 s on the 2-core box; one
        solve once sat 50 minutes in MUMPS on another machine.
    ramp_polish : bool
        On by default.  Polish a converged run whose residual fails the
        transient-band check and whose cost is within
        :data:`~ident.fit.core.POLISH_LEAD` of the fit's lowest converged cost so
        far (:func:`ident.fit.fit_gaps` decides; :meth:`polish` does it): with the
        nuisances, the continuation fits the skewed cosine (the load ramps' shape
        weights, :func:`ident.fit.model.ramp_shape`, held and not read), then
        one more solve at the last stage's width and horizon, from its solution
        and multipliers, on a second NLP of the same layout whose ramps read the
        weights (``FitModel.load_shaped``, built on first use), kept only where
        it converges to a lower cost.  :func:`ident.fit.fit_gaps` builds its
        model with the weights where this is on
        (``build_fit_model(ramp_weights=True)``).  The family nests the skewed
        cosine, so the polish can only take up ramp shape the cosine missed.
        Built into every NLP, the shape family made every stage dearer.  Freed
        through the continuation instead, the shapes take up what the wide
        kinks' rounding misses and lead the path elsewhere: plantsim hsm-f1
        seed 8201, from its true gaps, ended at a cost of 0.494 against 0.436
        with the cosine throughout; freed at the last width only, design starts
        on hsm-f1 seeds 4101 and 8400 ended at 2.54 and 2.05 against the
        cosine's 2.44 and 1.53.  Run after every converged solve (stop 38), it
        cost 70-124 s on fits that passed without it (plantsim hsm-f1 8401,
        8402) and took ``tests/test_fit_plant.py``'s hsm-f1 fit past 900 s.  On
        ``validation.fit_study --ramp-polish``, plant seeds 8400-8402 of both
        mills from the designed gaps (21 measured gaps, 900 s budget), accepted
        and right went from 43 % to 71 % (after every solve) and 81 % (only
        after a failed check, the baseline polished too; four of the six
        recordings measured before the baseline's polish), none accepted but
        wrong.  On by default with the leader rule (:data:`~ident.fit.core.POLISH_LEAD`),
        measured on another machine of this kind: the same 6 recordings 71 %
        (hsm-f1 8402's continuation ended at 0.438, passing the check under the
        allowance, against 0.337 on the first machine: rounding), seeds
        8400-8405 (42 measured gaps) 62 % accepted and right, 1 accepted but
        wrong (a series split that the polish does not touch), the full suite
        23:12 against 21:50 with it off.
    """

    degree: int = 3
    elements_per_sample: float | None = None
    max_phase: float = 1.5
    widths: tuple[float, ...] = (1e-3, 3e-4, 1e-4, 3e-5)
    horizons: tuple[float, ...] = (0.05, 0.08, 0.11, 0.14, 0.18, 0.22)
    tol: float = 1e-8
    max_iter: int = 300
    stage_tol: float | None = 1e-5
    stage_max_iter: int | None = None
    settle: tuple[float, ...] = (1e-3,)
    horizon_width: str = "first"
    compile: bool = True
    ipopt: Mapping[str, Any] = field(default_factory=dict)
    width_warm: str = "primal"
    max_cpu_s: float = 240.0
    ramp_polish: bool = True
    _cache: dict = field(default_factory=dict, compare=False, repr=False, hash=False)

    name = "collocation"

    def __post_init__(self) -> None:
        if not 1 <= int(self.degree) <= 9:
            raise FitError(f"Collocation degree must be 1..9. Got {self.degree}.")
        if not self.widths or any(w <= 0 for w in self.widths):
            raise FitError(f"Collocation widths must be positive. Got {self.widths}.")
        if self.width_warm not in ("primal", "duals"):
            raise FitError("Collocation width_warm must be 'primal' or 'duals'. "
                           f"Got {self.width_warm!r}.")
        if self.stage_max_iter is not None and self.stage_max_iter < 1:
            raise FitError(f"Collocation stage_max_iter must be >= 1. Got {self.stage_max_iter}.")
        if not self.max_cpu_s > 0:
            raise FitError(f"Collocation max_cpu_s must be positive. Got {self.max_cpu_s}.")
        if not self.max_phase > 0:
            raise FitError(f"Collocation max_phase must be positive. Got {self.max_phase}.")
        if self.elements_per_sample is not None:
            _ratio_shape(self.elements_per_sample)

    def block_shape(self, problem: Problem) -> tuple[int, int]:
        """(samples, elements) per block for this problem's mill and sample rate."""
        if self.elements_per_sample is not None:
            return _ratio_shape(self.elements_per_sample)
        from ..model.linear import natural_modes

        f = natural_modes(problem.model.mill).frequencies_hz
        f_max = float(np.max(f)) if len(f) else 0.0
        return element_shape(f_max, problem.dt, self.max_phase)

    # ---- building --------------------------------------------------------------------
    def nlp(self, problem: Problem, *, shaped: bool = False) -> CollocationNLP:
        """The NLP for this problem's structure (built once, then reused).

        ``shaped``: the one whose load ramps take the shape family
        (``FitModel.load_shaped``, the polish); the same layout as the other.
        """
        key = self._key(problem, shaped)
        got = self._cache.get(key)
        if got is None:
            got = _build(self, problem, shaped=shaped)
            self._cache[key] = got
        return got

    def nlp_of(self, problem: Problem, est: Estimate) -> CollocationNLP:
        """The NLP whose equations ``est`` (from :meth:`solve`) satisfies."""
        return self.nlp(problem, shaped=bool(est.extra.get("shaped", False)))

    # ---- solving ---------------------------------------------------------------------
    def solve(self, problem: Problem, start: Estimate, *, widths: Sequence[float] | None = None,
              horizons: Sequence[float] | None = None,
              schedule: Sequence[tuple[float, float | None]] | None = None,
              cpu_s: float | None = None) -> tuple[Estimate, SolveInfo]:
        """Fit ``problem`` from ``start``, continuing over the smoothing widths.

        A ``start`` that came out of this NLP (``start.extra["V"]``) warm-starts
        primal and dual variables; otherwise the collocation states are
        initialised by simulating the start.  ``cpu_s`` bounds the CPU seconds
        of the whole continuation (:func:`stage_cpu_cap`); where it runs out the
        solve stops unconverged with :data:`~ident.fit.problem.OUT_OF_TIME`.

        Returns
        -------
        Estimate, SolveInfo
        """
        t0 = time.perf_counter()
        new_build = not self._has(problem)
        build_s = 0.0
        nlp = self.nlp(problem)
        m = problem.model
        widths = tuple(widths if widths is not None else self.widths)
        if m.family is not Family.G1:
            widths = (widths[-1],)
        if schedule is None:
            schedule = _schedule(widths, self.horizons if horizons is None else horizons,
                                 self.horizon_width)
        else:
            schedule = [(float(w), h) for w, h in schedule]
            widths = tuple(w for w, _ in schedule)
        own = start.extra.get("nlp_key") == id(nlp)
        scales = start.extra["scales"] if own else _scales(problem, start, widths[0])
        V = start.extra["V"].copy() if own else _pack(nlp, problem, start, scales, widths[0])
        if own:
            V[:m.n_shared] = start.shared / scales["shs"]
        lbx, ubx = _bounds(nlp, problem, start, scales)
        V = np.clip(V, lbx, ubx)
        ramp_ix = _ramp_indices(nlp, problem)
        V[ramp_ix] = 0.0  # the skewed cosine (these NLPs do not read the weights)
        lbg, ubg = _constraint_bounds(nlp)
        lam_x = start.extra.get("lam_x") if own else None
        lam_g = start.extra.get("lam_g") if own else None
        stages = []
        total_it = 0
        status, success, cost = "Not_Started", False, math.nan
        cpu0 = time.thread_time()
        for k_stage, (w, hz) in enumerate(schedule):
            ts = time.perf_counter()
            cap = stage_cpu_cap(cpu_s, time.thread_time() - cpu0, self.max_cpu_s)
            if cap is not None and cap <= 0:
                status, success = OUT_OF_TIME, False
                break
            P = _params(nlp, problem, scales, w, hz)
            lo, hi = _held(lbx, ubx, ramp_ix, V)  # the ramps' shape weights: only the polish
            args = dict(x0=V, p=P, lbx=lo, ubx=hi, lbg=lbg, ubg=ubg)
            if self.width_warm == "primal" and k_stage and w != schedule[k_stage - 1][0]:
                lam_x = lam_g = None  # a sharper kink: the old multipliers mislead
            warm = lam_x is not None and lam_g is not None
            if warm:
                args.update(lam_x0=lam_x, lam_g0=lam_g)
            last = k_stage == len(schedule) - 1
            solver = nlp.solver(warm=warm, tol=None if last or self.stage_tol is None
                                else max(self.stage_tol, self.tol),
                                max_iter=None if last or self.stage_max_iter is None
                                else min(self.stage_max_iter, self.max_iter),
                                max_cpu_s=cap)
            sol, st, stage = _call(solver, args, w if m.family is Family.G1 else None, ts,
                                   stationary_ok=last)
            status, success, cost = stage.status, stage.success, stage.cost
            total_it += stage.iterations
            Vn = np.asarray(sol["x"]).ravel()
            stages.append(stage)
            if not np.all(np.isfinite(Vn)):
                success, status = False, "Invalid_Number_Detected"
                break
            V = Vn
            lam_x = np.asarray(sol["lam_x"]).ravel()
            lam_g = np.asarray(sol["lam_g"]).ravel()
        est = _unpack(nlp, problem, V, scales, widths[-1])
        est.extra.update({"lam_x": lam_x, "lam_g": lam_g, "scales": scales,
                          "width": float(widths[-1]), "shaped": False,
                          "horizon": schedule[-1][1] if schedule else None})
        L = nlp.layout
        info = SolveInfo(method=self.name, status=status, success=success,
                         iterations=total_it, seconds=time.perf_counter() - t0, cost=cost,
                         stages=tuple(stages),
                         build_seconds=(nlp.build_seconds if new_build else 0.0) + build_s,
                         nlp={"variables": nlp.n_x, "constraints": nlp.n_g,
                              "nnz_jacobian": L["nnz_jac"], "nnz_hessian": L["nnz_hess"],
                              "blocks": L["NB"], "elements": L["NB"] * L["ne"],
                              "elements_per_sample": nlp.elements_per_block
                              / nlp.samples_per_block,
                              "degree": nlp.degree})
        return est, info

    def polish(self, problem: Problem, est: Estimate, info: SolveInfo, *,
               cpu_s: float | None = None) -> tuple[Estimate, SolveInfo]:
        """The load ramps' shape freed in one more solve from ``est`` (the polish).

        ``est`` and ``info`` come out of :meth:`solve` on ``problem`` (the skewed
        cosine, the shape weights held at 0).  One warm solve at its last width and
        horizon on the NLP of the same layout whose ramps read the weights
        (``FitModel.load_shaped``, built on first use), from its solution and
        multipliers, at most :data:`POLISH_MAX_ITER` iterations (a call that stops
        there at a stationary cost counts as converged, :func:`stationary`).  Kept
        only where it converges to a lower cost; otherwise ``est`` and ``info`` come
        back with the attempt's stage recorded.  Nothing to polish (no weights in
        the model, no shared parameter free, an unconverged ``est``): unchanged.
        """
        nlp = self.nlp(problem)
        ramp_ix = _ramp_indices(nlp, problem)
        if not (ramp_ix.size and info.success and problem.free_shared.any()
                and est.extra.get("nlp_key") == id(nlp) and not est.extra.get("shaped")):
            return est, info
        cap = stage_cpu_cap(cpu_s, 0.0, self.max_cpu_s)
        if cap is not None and cap <= 0:
            return est, info
        m = problem.model
        ts = time.perf_counter()
        new_shaped = not self._has(problem, True)
        nlp_s = self.nlp(problem, shaped=True)  # the same layout, the shaped ramps
        scales, w, hz = est.extra["scales"], est.extra["width"], est.extra.get("horizon")
        lbx, ubx = _bounds(nlp, problem, est, scales)
        lbg, ubg = _constraint_bounds(nlp)
        # from the skewed cosine's optimum (weights 0): the family nests it
        args = dict(x0=est.extra["V"], p=_params(nlp_s, problem, scales, w, hz), lbx=lbx,
                    ubx=ubx, lbg=lbg, ubg=ubg)
        lam_x, lam_g = est.extra.get("lam_x"), est.extra.get("lam_g")
        warm = lam_x is not None and lam_g is not None
        if warm:  # from the optimum with the weights at their bound, unpushed
            lx = np.array(lam_x, dtype=float)
            lx[ramp_ix] = 0.0
            args.update(lam_x0=lx, lam_g0=lam_g)
        solver = nlp_s.solver(warm=warm, max_iter=min(POLISH_MAX_ITER, self.max_iter),
                              max_cpu_s=cap)
        sol, _, stage = _call(solver, args, w if m.family is Family.G1 else None, ts,
                              stationary_ok=True)
        status = stage.status
        stage = replace(stage, status=f"polish: {status}")
        V = np.asarray(sol["x"]).ravel()
        build_s = nlp_s.build_seconds if new_shaped else 0.0
        kept = stage.success and stage.cost < info.cost and bool(np.all(np.isfinite(V)))
        info = replace(info, iterations=info.iterations + stage.iterations,
                       seconds=info.seconds + (time.perf_counter() - ts),
                       build_seconds=info.build_seconds + build_s,
                       stages=info.stages + (stage,),
                       **({"cost": stage.cost, "status": status} if kept else {}))
        if not kept:
            return est, info
        out = _unpack(nlp, problem, V, scales, w)
        out.extra.update({"lam_x": np.asarray(sol["lam_x"]).ravel(),
                          "lam_g": np.asarray(sol["lam_g"]).ravel(), "scales": scales,
                          "width": float(w), "shaped": True, "horizon": hz})
        return out, info

    def _key(self, problem: Problem, shaped: bool) -> tuple:
        m = problem.model
        return (m.mill.content_hash(), m.family.value, m.shared_names, m.window_names,
                m.measured, tuple(e.name for e in m.effects), problem.lengths,
                round(problem.dt, 12), bool(shaped))

    def _has(self, problem: Problem, shaped: bool = False) -> bool:
        return self._key(problem, shaped) in self._cache

    def residual_vector(self, problem: Problem, est: Estimate) -> np.ndarray:
        """Weighted residuals (model - data) / channel std at ``est`` (from :meth:`solve`)."""
        nlp = self.nlp_of(problem, est)
        P = _params(nlp, problem, est.extra["scales"], est.extra["width"])
        return np.asarray(nlp.resid(est.extra["V"], P)).ravel()

    def residual_jacobian(self, problem: Problem, est: Estimate) -> tuple[np.ndarray, Any, Any]:
        """Weighted residuals, their sparse Jacobian and the constraints' Jacobian at ``est``.

        Everything in the NLP's scaled variables (``est`` must come out of
        :meth:`solve`); used by :mod:`ident.fit.uncertainty`.

        Returns
        -------
        r : ndarray, shape (n_residuals,)
        JR : scipy.sparse.csc_matrix, shape (n_residuals, n_x)
        JG : scipy.sparse.csc_matrix, shape (n_g, n_x)
        """
        nlp = self.nlp_of(problem, est)
        V = est.extra["V"]
        P = _params(nlp, problem, est.extra["scales"], est.extra["width"])
        r, jr = nlp.rjac(V, P)
        _, jg = nlp.gjac(V, P)
        return np.asarray(r).ravel(), _to_scipy(jr), _to_scipy(jg)


#: Status of a last stage that ran into its iteration or CPU bound at a stationary cost
#: (:func:`stationary`): converged for the verdict, and said so in its own words.
STATIONARY = "Stationary_At_Limit"

#: IPOPT iterations of :meth:`Collocation.polish`: on plantsim hsm-f1 8401 and 8402 it took
#: 213 (70 s, the cost 0.2 % lower) and ran out at 300 (124 s, 2 % lower, thrown away).
POLISH_MAX_ITER = 150

#: Granularity of :func:`stage_cpu_cap`, CPU s: each distinct cap is an IPOPT instance.
CPU_CAP_STEP = 5.0


def stage_cpu_cap(cpu_s: float | None, used: float, max_cpu_s: float) -> float | None:
    """CPU seconds the next stage of a solve bounded by ``cpu_s`` may take.

    None where the stage's own bound ``max_cpu_s`` is the tighter (or there is
    no ``cpu_s``); 0 where nothing is left; otherwise what is left, rounded up
    to :data:`CPU_CAP_STEP` (a few distinct IPOPT instances, not one per stage).
    """
    if cpu_s is None:
        return None
    left = float(cpu_s) - float(used)
    if left <= 0:
        return 0.0
    cap = math.ceil(left / CPU_CAP_STEP) * CPU_CAP_STEP
    return None if cap >= max_cpu_s else cap

#: Iterations over which :func:`stationary` looks at the cost, and the relative change
#: it allows there.  The cost is half the mean squared weighted residual over ~10^4
#: samples, so moving a gap by one standard error changes it by ~1e-4 of itself:
#: 1e-5 over 30 iterations is a creep along the kink, not a descent.
STATIONARY_ITER = 30
STATIONARY_REL = 1e-5

#: Largest constraint violation (collocation defects, scaled) of a stationary end.
STATIONARY_INF_PR = 1e-6


def _last_inf_pr(stats: Mapping[str, Any]) -> float:
    """The constraint violation of an IPOPT call's last iterate (NaN if not recorded)."""
    pr = list((stats.get("iterations") or {}).get("inf_pr", []))
    return float(pr[-1]) if pr else math.nan


def stationary(stats: Mapping[str, Any]) -> bool:
    """Whether an IPOPT call that hit a bound ended at a stationary cost.

    The kink of the last width (3e-5 rad) makes IPOPT's dual infeasibility
    creep: on a plant recording (plantsim cold-s5, seed 4102) the last stage
    spent 300 iterations with the cost changing by 2e-7 of itself, feasible to
    2e-9, and its dual infeasibility at 3e-6 (the acceptable level is 1e-6,
    ten iterations in a row), the gaps 0.05 % (a twentieth of their standard
    errors) from a start nudged by 1e-6 that converged.  Counting that as a failure threw the fit away and ran every
    other path (437 s against 90 s).

    True when the call stopped at ``Maximum_Iterations_Exceeded`` or
    ``Maximum_CpuTime_Exceeded``, its cost changed by at most
    :data:`STATIONARY_REL` of itself over the last :data:`STATIONARY_ITER`
    iterations, and its last constraint violation is at most
    :data:`STATIONARY_INF_PR`.
    """
    if str(stats.get("return_status")) not in ("Maximum_Iterations_Exceeded",
                                                 "Maximum_CpuTime_Exceeded"):
        return False
    obj = list((stats.get("iterations") or {}).get("obj", []))
    pr = _last_inf_pr(stats)
    if len(obj) <= STATIONARY_ITER or not math.isfinite(pr):
        return False
    a, b = float(obj[-1 - STATIONARY_ITER]), float(obj[-1])
    if not (math.isfinite(a) and math.isfinite(b)):
        return False
    return bool(abs(a - b) <= STATIONARY_REL * max(abs(b), 1e-12)
                and pr <= STATIONARY_INF_PR)


def _ratio_shape(elements_per_sample: float) -> tuple[int, int]:
    """(samples, elements) per block of an explicit ``elements_per_sample``."""
    f = Fraction(elements_per_sample).limit_denominator(8)
    if f <= 0 or abs(float(f) - elements_per_sample) > 1e-9 or f.numerator > 8:
        raise FitError("Collocation elements_per_sample must be a ratio of small integers "
                       f"such as 0.5, 1 or 2. Got {elements_per_sample}.")
    return f.denominator, f.numerator


#: Most samples one element spans (and most elements one sample holds).
MAX_PER_BLOCK = 8


def element_shape(f_max_hz: float, dt: float, max_phase: float) -> tuple[int, int]:
    """(samples, elements) per block: the longest element ``h`` with ``2 pi f_max h <= max_phase``.

    Parameters
    ----------
    f_max_hz : float
        Highest natural frequency to resolve, Hz (0: no bound).
    dt : float
        Sample interval, s.
    max_phase : float
        Phase of ``f_max`` over one element, rad.

    Returns
    -------
    (int, int)
        Up to :data:`MAX_PER_BLOCK` samples per element when an element may
        span several samples, else one sample split into up to that many
        elements.
    """
    if not f_max_hz > 0:
        return MAX_PER_BLOCK, 1
    per = max_phase / (2.0 * math.pi * f_max_hz * dt)  # samples one element may span
    if per >= 1.0:
        return min(int(math.floor(per + 1e-9)), MAX_PER_BLOCK), 1
    return 1, min(int(math.ceil(1.0 / per - 1e-9)), MAX_PER_BLOCK)


def _schedule(widths: Sequence[float], horizons: Sequence[float],
              at: str) -> list[tuple[float, float | None]]:
    """Continuation stages ``(width, horizon)``: horizons at the first or the last width."""
    widths = tuple(widths)
    hz = tuple(horizons)
    if not hz:
        return [(w, None) for w in widths]
    if at == "first":
        return [(widths[0], h) for h in hz] + [(w, None) for w in widths]
    # the widths on the first horizon, then the horizon extended at the final width
    return [(w, hz[0]) for w in widths] + [(widths[-1], h) for h in hz[1:]] + [
        (widths[-1], None)]


def _warm_options() -> dict[str, Any]:
    return {"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-9,
            "ipopt.warm_start_mult_bound_push": 1e-9, "ipopt.mu_init": 1e-5,
            "ipopt.warm_start_slack_bound_push": 1e-9}


def _to_scipy(M: Any) -> Any:
    sp = M.sparsity()
    colptr = np.asarray(sp.colind())
    rows = np.asarray(sp.row())
    return sps.csc_matrix((np.asarray(M.nonzeros()), rows, colptr), shape=M.shape)


# ---- the state layout -----------------------------------------------------------------
def _state_parts(m: Any) -> dict[str, Any]:
    """Indices of angles, speeds, loop integral and effect states in the driveline state."""
    n = len(m.mill.masses)
    nx = m.nx
    return {"n": n, "theta": np.arange(n), "omega": np.arange(n, 2 * n), "z": 2 * n,
            "extra": np.arange(2 * n + 1, nx), "nxe": nx - 2 * n - 1}


def _compiled(fn: Any) -> Any:
    """``fn`` generated as C and compiled (cached on disk by its source), or None."""
    from ..model.integrate import _compile

    try:
        return _compile(fn, "ident_coll_" + fn.name())
    except (OSError, RuntimeError):  # pragma: no cover - no compiler or no cache dir
        return None


def _block_functions(m: Any, *, d: int, ns: int, ne: int, dt: float,
                     compile: bool = False, shaped: bool = False) -> dict[str, Any]:
    """SX functions of one block (``ns`` samples, ``ne`` elements) and their derivatives.

    Block variables (scaled) ``z = [theta_k; omega_k; extra_k; per element (vec(Q);
    v_end; vec(E)); shared; window; z0]`` with ``Q`` the angles at the
    collocation points (n x d), ``v_end`` the speeds at the element's end and
    ``E`` effect states at the collocation points.
    """
    drv = m.driveline
    load = m.load_shaped if shaped and m.load_shaped is not None else m.load
    sp = _state_parts(m)
    n, nxe, nx, ny = sp["n"], sp["nxe"], m.nx, m.ny
    im = m.motor_index
    h = ns * dt / ne
    tau = np.array([0.0] + list(ca.collocation_points(d, "radau")))
    C, polys = _lagrange(tau)
    nsh, nwin = m.n_shared, m.n_window
    n_start = 2 * n + nxe
    n_el = n * d + n + nxe * d
    nz = n_start + ne * n_el + nsh + nwin + 1
    zv = ca.SX.sym("z", nz)
    ym = ca.SX.sym("ym", ny * ns + ns)  # samples, then one weight per sample
    t0 = ca.SX.sym("t0")
    w = ca.SX.sym("w")
    wy = ca.SX.sym("wy", ny)
    ths = ca.SX.sym("ths", n)
    oms = ca.SX.sym("oms", n)
    exs = ca.SX.sym("exs", nxe)
    shs = ca.SX.sym("shs", nsh)
    wis = ca.SX.sym("wis", nwin + 1)
    o = n_start + ne * n_el
    sh = zv[o:o + nsh] * shs
    winz = zv[o + nsh:] * wis
    win = winz[:nwin]
    z0 = winz[nwin]
    p = m.pmap(sh, win, w)
    th_k = zv[:n] * ths
    om_k = zv[n:2 * n] * oms
    ex_k = zv[2 * n:n_start] * exs
    defs = []
    elems = []
    for e in range(ne):
        b = n_start + e * n_el
        Q = ca.reshape(zv[b:b + n * d], n, d)
        v_end = zv[b + n * d:b + n * d + n] * oms
        E = ca.reshape(zv[b + n * d + n:b + n_el], nxe, d) if nxe else None
        T = [th_k] + [Q[:, r] * ths for r in range(d)]
        X = [ex_k] + ([E[:, r] * exs for r in range(d)] if nxe else [ex_k] * d)
        W = [om_k] + [sum(C[j, r] * T[j] for j in range(d + 1)) / h for r in range(1, d + 1)]
        # the speed variable at the element's end is the angle polynomial's slope there
        defs.append((v_end - W[d]) / oms)
        W[d] = v_end
        for r in range(1, d + 1):
            tr = t0 + (e + tau[r]) * h
            x = ca.vertcat(T[r], W[r], z0 - T[r][im], X[r])
            f = drv.rhs(x, load(tr, win), p, tr)
            acc = sum(C[j, r] * W[j] for j in range(d + 1))
            defs.append((acc - h * f[n:2 * n]) / oms)
            if nxe:
                dxe = sum(C[j, r] * X[j] for j in range(d + 1))
                defs.append((dxe - h * f[2 * n + 1:]) / exs)
        elems.append((T, W, X))
        th_k, om_k, ex_k = T[d], W[d], X[d]
    res = []
    xsamp = []
    for j in range(ns):
        tj = j * dt
        e = min(int(math.floor(tj / h + 1e-9)), ne - 1)
        tl = tj / h - e
        T, W, X = elems[e]
        c = [float(polys[i](tl)) for i in range(d + 1)]
        th = sum(c[i] * T[i] for i in range(d + 1))
        om = sum(c[i] * W[i] for i in range(d + 1))
        xe = sum(c[i] * X[i] for i in range(d + 1)) if nxe else ca.SX(0, 1)
        x = ca.vertcat(th, om, z0 - th[im], xe)
        xsamp.append(x)
        yj = m.y(x, load(t0 + tj, win), p, t0 + tj, win)
        res.append((yj - ym[j * ny:(j + 1) * ny]) * wy * ym[ny * ns + j])
    G = ca.vertcat(*defs)
    R = ca.vertcat(*res)
    ins = [zv, ym, t0, w, wy, ths, oms, exs, shs, wis]
    names = ["z", "ym", "t0", "w", "wy", "ths", "oms", "exs", "shs", "wis"]
    JR = ca.jacobian(R, zv)
    JG = ca.jacobian(G, zv)
    sigma = ca.SX.sym("sigma")
    lam = ca.SX.sym("lam", G.numel())
    H, _ = ca.hessian(sigma * 0.5 * ca.sumsqr(R) + ca.dot(lam, G), zv)
    out = {
        "block": ca.Function("block", ins, [G, R], names, ["G", "R"]),
        "grad": ca.Function("block_grad", ins, [0.5 * ca.sumsqr(R), ca.mtimes(JR.T, R)],
                            names, ["fb", "gz"]),
        "jac": ca.Function("block_jac", ins, [JG], names, ["JG"]),
        "rjac": ca.Function("block_rjac", ins, [JR], names, ["JR"]),
        "hess": ca.Function("block_hess", ins + [sigma, lam], [H], names + ["sigma", "lam"],
                            ["H"]),
        "samples": ca.Function("block_samples", ins, [ca.horzcat(*xsamp)], names, ["X"]),
        "nz": nz, "nG": int(G.numel()), "nR": int(R.numel()), "tau": tau,
        "n_start": n_start, "n_el": n_el, "mono": None,
    }
    if compile:
        for k in ("grad", "jac", "rjac", "hess"):  # f and g stay differentiable
            out[k] = _compiled(out[k]) or out[k]
    if m.family is Family.G2:
        shv = ca.SX.sym("sh", nsh)
        shsv = ca.SX.sym("shs", nsh)
        a = shv * shsv
        cons = []
        for el in m.mill.elements:
            i1, i2, i3 = (m.shared_names.index(f"{el.id}.{k}") for k in ("a1", "a2", "a3"))
            sc = float(m.shared_scale[i1] * m.shared_scale[i3])
            cons.append((3 * a[i1] * a[i3] - a[i2] * a[i2]) / sc)
        cv = ca.vertcat(*cons)
        lm = ca.SX.sym("lm", cv.numel())
        Hm, _ = ca.hessian(ca.dot(lm, cv), shv)
        out["mono"] = ca.Function("mono", [shv, shsv], [cv])
        out["mono_jac"] = ca.Function("mono_jac", [shv, shsv], [ca.densify(ca.jacobian(cv, shv))])
        out["mono_hess"] = ca.Function("mono_hess", [shv, shsv, lm], [ca.densify(Hm)])
    return out


def _build(strategy: Collocation, problem: Problem, *, shaped: bool = False) -> CollocationNLP:
    t_start = time.perf_counter()
    m = problem.model
    ny, d = m.ny, int(strategy.degree)
    ns, ne = strategy.block_shape(problem)
    dt = problem.dt
    n_blocks = []
    for n_s in problem.lengths:
        nb = (n_s - 1) // ns
        if nb < 2:
            raise FitError(f"a window of {n_s} samples is too short for {ns} samples per block.")
        n_blocks.append(nb)
    blk = _block_functions(m, d=d, ns=ns, ne=ne, dt=dt, compile=strategy.compile, shaped=shaped)
    sp = _state_parts(m)
    n, nxe = sp["n"], sp["nxe"]
    nz, nG, nR = blk["nz"], blk["nG"], blk["nR"]
    n_start, n_el = blk["n_start"], blk["n_el"]

    # ---- layout of the decision vector: [shared; per window (window, z0); x0 starts; elements]
    nw = len(n_blocks)
    NB = sum(n_blocks)
    nsh, nwin = m.n_shared, m.n_window + 1
    o_win = nsh
    o_x0 = o_win + nwin * nw
    o_el = o_x0 + n_start * nw
    n_var = o_el + n_el * ne * NB
    # offsets of the last state (theta, omega, extra) inside an element vector
    last_th = np.arange(n * (d - 1), n * d)
    last_om = np.arange(n * d, n * d + n)
    last_ex = n * d + n + np.arange(nxe * (d - 1), nxe * d)
    last = np.concatenate([last_th, last_om, last_ex])
    idx = np.empty((nz, NB), dtype=np.int64)
    t0s = np.empty(NB)
    first_el = []
    el = 0
    b = 0
    for i, nb in enumerate(n_blocks):
        first_el.append(el)
        for k in range(nb):
            if k == 0:
                start = o_x0 + n_start * i + np.arange(n_start)
            else:
                start = o_el + n_el * (el - 1) + last
            els = o_el + n_el * el + np.arange(n_el * ne)
            idx[:, b] = np.concatenate([start, els, np.arange(nsh),
                                        o_win + nwin * i + np.arange(nwin)])
            t0s[b] = k * ns * dt
            el += ne
            b += 1

    V = ca.MX.sym("V", n_var)
    P_w = ca.MX.sym("w")
    P_wy = ca.MX.sym("wy", ny)
    P_ths = ca.MX.sym("ths", n)
    P_oms = ca.MX.sym("oms", n)
    P_exs = ca.MX.sym("exs", nxe)
    P_shs = ca.MX.sym("shs", nsh)
    P_wis = ca.MX.sym("wis", nwin)
    P_Y = ca.MX.sym("Y", nR + ns, NB)
    P = ca.vertcat(P_w, P_wy, P_ths, P_oms, P_exs, P_shs, P_wis, ca.vec(P_Y))
    lam_f = ca.MX.sym("lam_f")
    Z = V[ca.DM(idx.astype(float))]
    bargs = [Z, P_Y, ca.DM(t0s[None, :]), P_w, P_wy, P_ths, P_oms, P_exs, P_shs, P_wis]
    G, R = blk["block"].map(NB, "serial")(*bargs)
    f = 0.5 * ca.sumsqr(R)
    mono = blk["mono"]
    n_mono = mono.size1_out(0) if mono is not None else 0
    sh_v = V[:nsh]
    g = ca.vertcat(ca.vec(G), mono(sh_v, P_shs)) if n_mono else ca.vec(G)
    n_g = NB * nG + n_mono
    lam_g = ca.MX.sym("lam_g", n_g)

    # objective gradient: block gradients summed into place (dense: IPOPT reads all of it)
    fb, gz = blk["grad"].map(NB, "serial")(*bargs)
    A_grad = sps.csc_matrix((np.ones(nz * NB), (idx.ravel(order="F"), np.arange(nz * NB))),
                            shape=(n_var, nz * NB))
    grad_f = ca.densify(ca.mtimes(ca.DM(A_grad), ca.vec(gz)))
    grad_fn = ca.Function("nlp_grad_f", [V, P], [ca.sum2(fb), grad_f])

    # constraint Jacobian: block Jacobians placed by rows and columns
    JG = blk["jac"].map(NB, "serial")(*bargs)
    rj, cj = _triplets(blk["jac"].sparsity_out(0))
    rows = (np.arange(NB)[:, None] * nG + rj[None, :]).ravel()
    cols = idx[cj[:, None], np.arange(NB)[None, :]].T.ravel()
    src = [_nonzeros(JG)]
    if n_mono:
        mj = blk["mono_jac"](sh_v, P_shs)
        mr, mc = np.nonzero(np.ones((n_mono, nsh)))
        rows = np.concatenate([rows, NB * nG + mr])
        cols = np.concatenate([cols, mc])
        src.append(ca.vec(mj.T))
    sp_jac, perm = _ccs(rows, cols, (n_g, n_var))
    jac = ca.sparsity_cast(ca.vertcat(*src)[perm.tolist()], sp_jac)
    jac_fn = ca.Function("nlp_jac_g", [V, P], [g, jac])

    # Lagrangian Hessian: block Hessians summed, upper triangle
    H = blk["hess"].map(NB, "serial")(*bargs, lam_f, ca.reshape(lam_g[:NB * nG], nG, NB))
    rh, chh = _triplets(blk["hess"].sparsity_out(0))
    gr = idx[rh[:, None], np.arange(NB)[None, :]].T.ravel()
    gc = idx[chh[:, None], np.arange(NB)[None, :]].T.ravel()
    srcid = np.arange(NB * len(rh))
    keep = gr <= gc
    gr, gc, srcid = gr[keep], gc[keep], srcid[keep]
    hsrc = [_nonzeros(H)]
    n_src = NB * len(rh)
    if n_mono:
        mh = blk["mono_hess"](sh_v, P_shs, lam_g[NB * nG:])
        r2, c2 = np.nonzero(np.triu(np.ones((nsh, nsh))))
        gr = np.concatenate([gr, r2])
        gc = np.concatenate([gc, c2])
        srcid = np.concatenate([srcid, n_src + r2 + nsh * c2])
        hsrc.append(ca.vec(mh))
        n_src += nsh * nsh
    sp_h, A_h = _summed_ccs(gr, gc, srcid, (n_var, n_var), n_src)
    hess = ca.sparsity_cast(ca.mtimes(ca.DM(A_h), ca.vertcat(*hsrc)), sp_h)
    hess_fn = ca.Function("nlp_hess_l", [V, P, lam_f, lam_g], [hess])

    # residual Jacobian and states at the samples (after the solve)
    JR = blk["rjac"].map(NB, "serial")(*bargs)
    rr, cr = _triplets(blk["rjac"].sparsity_out(0))
    rows = (np.arange(NB)[:, None] * nR + rr[None, :]).ravel()
    cols = idx[cr[:, None], np.arange(NB)[None, :]].T.ravel()
    sp_r, perm_r = _ccs(rows, cols, (NB * nR, n_var))
    jr = ca.sparsity_cast(_nonzeros(JR)[perm_r.tolist()], sp_r)
    rjac_fn = ca.Function("rjac", [V, P], [ca.vec(R), jr])
    samples_fn = ca.Function("samples", [V, P], [blk["samples"].map(NB, "serial")(*bargs)])

    opts = {
        "ipopt.hessian_approximation": "exact",
        "ipopt.mumps_permuting_scaling": 0,
        "ipopt.mumps_scaling": 0,
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "calc_lam_p": False,
        "ipopt.tol": strategy.tol,
        "ipopt.acceptable_tol": 1e-6,
        "ipopt.acceptable_iter": 10,
        "ipopt.max_iter": strategy.max_iter,
        "ipopt.max_cpu_time": float(strategy.max_cpu_s),
        "ipopt.nlp_scaling_method": "none",
        "grad_f": grad_fn,
        "jac_g": jac_fn,
        "hess_lag": hess_fn,
    }
    user = {k if k.startswith("ipopt.") else f"ipopt.{k}": v for k, v in strategy.ipopt.items()}
    opts.update(user)
    prob = {"x": V, "p": P, "f": f, "g": g}
    cold = ca.nlpsol("ident_coll", "ipopt", prob, opts)
    wopts = dict(opts)
    wopts.update(_warm_options())
    wopts.update(user)
    warm = ca.nlpsol("ident_coll_warm", "ipopt", prob, wopts)
    layout = {"nsh": nsh, "nwin": nwin, "nw": nw, "n": n, "nxe": nxe, "ny": ny, "ns": ns,
              "ne": ne, "o_win": o_win, "o_x0": o_x0, "o_el": o_el, "n_start": n_start,
              "n_el": n_el, "first_el": first_el, "n_mono": n_mono, "nG": nG, "nR": nR,
              "NB": NB, "nnz_jac": int(sp_jac.nnz()), "nnz_hess": int(sp_h.nnz())}
    return CollocationNLP(cold=cold, warm=warm, n_blocks=tuple(n_blocks), samples_per_block=ns,
                          elements_per_block=ne, degree=d, tau_root=blk["tau"], layout=layout,
                          n_x=n_var, n_g=n_g, build_seconds=time.perf_counter() - t_start,
                          rjac=rjac_fn, gjac=jac_fn, samples=samples_fn,
                          resid=ca.Function("resid", [V, P], [ca.vec(R)]),
                          lengths=problem.lengths, definition=prob, options=opts)


def _nonzeros(M: Any) -> Any:
    """The structural nonzeros of an MX matrix as a column (no copy of zeros)."""
    return ca.sparsity_cast(M, ca.Sparsity.dense(M.nnz(), 1))


def _triplets(sp: Any) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of each nonzero of a CasADi sparsity, in its (CCS) order."""
    r, c = sp.get_triplet()
    return np.asarray(r, dtype=np.int64), np.asarray(c, dtype=np.int64)


def _ccs(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> tuple[Any, np.ndarray]:
    """CasADi sparsity of distinct (rows, cols) and the permutation into its CCS order."""
    order = np.lexsort((rows, cols))
    r, c = rows[order], cols[order]
    colptr = np.searchsorted(c, np.arange(shape[1] + 1))
    return ca.Sparsity(shape[0], shape[1], colptr.tolist(), r.tolist()), order


def _summed_ccs(rows: np.ndarray, cols: np.ndarray, src: np.ndarray, shape: tuple[int, int],
                n_src: int) -> tuple[Any, Any]:
    """Sparsity of the distinct (rows, cols) and the 0/1 matrix summing sources into it."""
    key = cols.astype(np.int64) * shape[0] + rows
    uniq, inv = np.unique(key, return_inverse=True)
    ur = (uniq % shape[0]).astype(np.int64)
    uc = (uniq // shape[0]).astype(np.int64)
    colptr = np.searchsorted(uc, np.arange(shape[1] + 1))
    sp = ca.Sparsity(shape[0], shape[1], colptr.tolist(), ur.tolist())
    A = sps.csc_matrix((np.ones(len(src)), (inv, src)), shape=(len(uniq), n_src))
    return sp, A


# ---- packing ---------------------------------------------------------------------------
def _scales(problem: Problem, est: Estimate, w0: float) -> dict:
    m = problem.model
    sp = _state_parts(m)
    trajs = est.trajectories if est.trajectories is not None else simulate_estimate(
        problem, est, w=w0)
    allx = np.abs(np.concatenate(trajs, axis=0))
    mx = np.max(allx, axis=0)
    ths = np.maximum(mx[sp["theta"]], 1e-4)
    oms = np.maximum(mx[sp["omega"]], 1e-3)
    exs = np.maximum(mx[sp["extra"]], 1e-6) if sp["nxe"] else np.zeros(0)
    wis = np.max(np.stack([problem.window_bounds(i)[2] for i in range(problem.n_windows)]),
                 axis=0)
    zs = max(float(mx[sp["z"]]), 1e-3)
    return {"ths": ths, "oms": oms, "exs": exs, "shs": m.shared_scale.copy(),
            "wis": np.concatenate([wis, [zs]]), "trajs": trajs}


def _params(nlp: CollocationNLP, problem: Problem, scales: dict, w: float,
            horizon: float | None = None) -> np.ndarray:
    """NLP parameters: width, weights, scales, data and per-sample weights.

    ``horizon`` (s after each window's ``t_step``): samples later than that
    weigh nothing (horizon continuation); ``None`` weighs all.
    """
    L = nlp.layout
    ns, ny = L["ns"], L["ny"]
    Ys = []
    for i, nb in enumerate(nlp.n_blocks):
        y = problem.y[i][:nb * ns]
        wt = np.ones(nb * ns)
        if horizon is not None:
            win = problem.windows[i]
            t_rel = np.arange(nb * ns) * problem.dt
            wt = (t_rel <= (win.t_step - win.t[0]) + horizon).astype(float)
        Ys.append(np.vstack([y.reshape(nb, ns * ny).T, wt.reshape(nb, ns).T]))
    Y = np.concatenate(Ys, axis=1)
    return np.concatenate([[w], 1.0 / problem.y_scale, scales["ths"], scales["oms"],
                           scales["exs"], scales["shs"], scales["wis"], Y.ravel(order="F")])


def _bounds(nlp: CollocationNLP, problem: Problem, est: Estimate,
            scales: dict) -> tuple[np.ndarray, np.ndarray]:
    L = nlp.layout
    m = problem.model
    lb = np.full(nlp.n_x, -np.inf)
    ub = np.full(nlp.n_x, np.inf)
    free = problem.free_shared
    lb[:L["nsh"]] = np.where(free, m.shared_lb, est.shared) / scales["shs"]
    ub[:L["nsh"]] = np.where(free, m.shared_ub, est.shared) / scales["shs"]
    for i in range(L["nw"]):
        wl, wu, _ = problem.window_bounds(i)
        o = L["o_win"] + i * L["nwin"]
        lb[o:o + L["nwin"] - 1] = wl / scales["wis"][:-1]
        ub[o:o + L["nwin"] - 1] = wu / scales["wis"][:-1]
        for j in m.x0_fixed:
            lb[L["o_x0"] + i * L["n_start"] + j] = 0.0
            ub[L["o_x0"] + i * L["n_start"] + j] = 0.0
    return lb, ub


def _call(solver: Any, args: dict, width: float | None, t_start: float, *,
          stationary_ok: bool = False) -> tuple[Any, Mapping[str, Any], StageInfo]:
    """One IPOPT call: its solution, stats and stage record (``stationary_ok``: a call
    that stopped at a bound at a stationary cost counts as converged, :func:`stationary`)."""
    sol = solver(**args)
    st = solver.stats()
    status = str(st.get("return_status", "unknown"))
    success = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level")
    if stationary_ok and not success and stationary(st):
        status, success = STATIONARY, True
    stage = StageInfo(width=None if width is None else float(width), status=status,
                      success=success, iterations=int(st.get("iter_count", 0)),
                      seconds=time.perf_counter() - t_start, cost=float(sol["f"]),
                      infeasibility=_last_inf_pr(st))
    return sol, st, stage


def _constraint_bounds(nlp: CollocationNLP) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the constraints: equalities, then the monotonicity rows (>= 0)."""
    lbg = np.zeros(nlp.n_g)
    ubg = np.zeros(nlp.n_g)
    if nlp.layout["n_mono"]:
        ubg[-nlp.layout["n_mono"]:] = np.inf
    return lbg, ubg


def _held(lb: np.ndarray, ub: np.ndarray, ix: np.ndarray,
          V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds with the variables at ``ix`` fixed at their values in ``V``."""
    if not ix.size:
        return lb, ub
    lo, hi = lb.copy(), ub.copy()
    lo[ix] = hi[ix] = V[ix]
    return lo, hi


def _ramp_indices(nlp: CollocationNLP, problem: Problem) -> np.ndarray:
    """Positions of every window's ramp-shape weights in the decision vector."""
    from .model import RAMP_PARAMS

    L = nlp.layout
    names = problem.model.window_names
    cols = [names.index(nm) for nm in RAMP_PARAMS if nm in names]
    return np.array([L["o_win"] + i * L["nwin"] + j for i in range(L["nw"]) for j in cols],
                    dtype=int)


def _pack(nlp: CollocationNLP, problem: Problem, est: Estimate, scales: dict,
          w0: float) -> np.ndarray:
    L = nlp.layout
    m = problem.model
    sp = _state_parts(m)
    n, nxe = sp["n"], sp["nxe"]
    d, ne, ns = nlp.degree, L["ne"], L["ns"]
    h = ns * problem.dt / ne
    V = np.zeros(nlp.n_x)
    V[:L["nsh"]] = est.shared / scales["shs"]
    trajs = scales["trajs"]
    tk = None
    xs_full = np.concatenate([scales["ths"], scales["oms"], [1.0], scales["exs"]])
    for i, nb in enumerate(nlp.n_blocks):
        o = L["o_win"] + i * L["nwin"]
        V[o:o + L["nwin"] - 1] = est.window[i] / scales["wis"][:-1]
        V[o + L["nwin"] - 1] = est.x0[i][sp["z"]] / scales["wis"][-1]
        x0 = est.x0[i]
        V[L["o_x0"] + i * L["n_start"]:L["o_x0"] + (i + 1) * L["n_start"]] = np.concatenate(
            [x0[sp["theta"]] / scales["ths"], x0[sp["omega"]] / scales["oms"],
             x0[sp["extra"]] / scales["exs"] if nxe else []])
        traj = trajs[i]
        tk = np.arange(traj.shape[0]) * problem.dt
        n_els = nb * ne
        t_el = np.arange(n_els)[:, None] * h + nlp.tau_root[None, 1:] * h  # (n_els, d)
        Xi = np.stack([np.interp(t_el.ravel(), tk, traj[:, c]) for c in range(m.nx)], axis=1)
        Xi = Xi.reshape(n_els, d, m.nx) / xs_full[None, None, :]
        blockv = np.concatenate([
            Xi[:, :, sp["theta"]].reshape(n_els, d * n),
            Xi[:, d - 1, sp["omega"]],
            Xi[:, :, sp["extra"]].reshape(n_els, d * nxe) if nxe else np.zeros((n_els, 0)),
        ], axis=1)
        o = L["o_el"] + L["n_el"] * L["first_el"][i]
        V[o:o + L["n_el"] * n_els] = blockv.ravel()
    return V


def _unpack(nlp: CollocationNLP, problem: Problem, V: np.ndarray, scales: dict,
            w: float) -> Estimate:
    L = nlp.layout
    m = problem.model
    sp = _state_parts(m)
    shared = V[:L["nsh"]] * scales["shs"]
    Wz = V[L["o_win"]:L["o_x0"]].reshape(L["nw"], L["nwin"]) * scales["wis"][None, :]
    window = Wz[:, :-1]
    x0 = np.zeros((L["nw"], m.nx))
    for i in range(L["nw"]):
        s = V[L["o_x0"] + i * L["n_start"]:L["o_x0"] + (i + 1) * L["n_start"]]
        x0[i, sp["theta"]] = s[:sp["n"]] * scales["ths"]
        x0[i, sp["omega"]] = s[sp["n"]:2 * sp["n"]] * scales["oms"]
        x0[i, sp["z"]] = Wz[i, -1]
        if sp["nxe"]:
            x0[i, sp["extra"]] = s[2 * sp["n"]:] * scales["exs"]
    Xs = np.asarray(nlp.samples(V, _params(nlp, problem, scales, w)))  # nx x (ns*NB)
    trajs = []
    c = 0
    for nb in nlp.n_blocks:
        trajs.append(Xs[:, c * L["ns"]:(c + nb) * L["ns"]].T.copy())
        c += nb
    return Estimate(shared=shared, window=window, x0=x0, trajectories=tuple(trajs),
                    extra={"V": V.copy(), "nlp_key": id(nlp)})


def simulate_estimate(problem: Problem, est: Estimate, *, w: float,
                      n_sub: int = 2) -> tuple[np.ndarray, ...]:
    """State trajectories (N_w, nx) of every window simulated from an estimate."""
    from .simulator import build_simulator

    sims: dict[int, Any] = {}
    out = []
    for i, win in enumerate(problem.windows):
        n_s = win.n_samples
        if n_s not in sims:
            sims[n_s] = build_simulator(problem.model, n_s, problem.dt, n_sub=n_sub,
                                        sensitivities=False)
        _, X = sims[n_s].simulate(est.x0[i], est.shared, est.window[i], w)
        if not np.all(np.isfinite(X)):
            X = np.repeat(est.x0[i][None, :], n_s, axis=0)
        out.append(X)
    return tuple(out)
