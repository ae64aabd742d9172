"""Levenberg-Marquardt on sparse normal equations (Nielsen's damping update).

The problem gives, at x, the Gauss-Newton system H (a WindowSystem), the gradient g = J^T W r
and the cost F = 0.5 r^T W r. Each iteration is four steps:

- propose: solve (H + lambda D) dx = -g with D = diag(H) (Marquardt; clamped below by
  `damping_floor` * mean |diag H| so unconstrained coordinates still get damped) or D = I.
  A damped system that is not positive definite (the paper's raw Neo-Hookean prior can make H
  indefinite; Cholesky or PCG reports it) proposes nothing. The problem's
  `step_fraction(x, dx)` (optional) gives the largest fraction alpha of the step that keeps
  every element's volume above its margin, one for the whole step or one per unknown (a
  factor graph cuts each state's part on its own), so a step that would invert a tetrahedron
  is shortened, not thrown away.
- judge: the proposed step alpha dx is accepted when its gain ratio
      rho = (F(x) - F(x + alpha dx)) / (L(0) - L(alpha dx)),
      L(0) - L(alpha dx) = -alpha g.dx - 0.5 alpha^2 dx.H dx
  is positive.
- adapt the damping: after an accepted step lambda *= max(1/3, 1 - (2 rho - 1)^3) and nu = 2
  (Nielsen 1999 / Madsen-Nielsen-Tingleff); after a rejected one lambda *= nu, nu *= 2; a
  shortened step also doubles lambda (the model's step reached past the feasible region, so
  the next one should be shorter).
- test convergence. "Converged" means an optimality test holds at the returned x, never that
  no step could be taken:
    "gradient":  |g|_inf <= gradient_tolerance * max(1, |g_0|_inf);
    "decrement": the Newton decrement 0.5 g^T H^-1 g of the undamped model, estimated with the
                 solver's preconditioner (`solver.decrement`), is below the cost tolerance
                 max(absolute_cost_tolerance, cost_tolerance * F);
    "predicted decrease": a full proposed step would lower the model by less than the cost
                 tolerance (it is then not taken);
    "cost":      an accepted full step lowered F by less than the cost tolerance;
    "step":      an accepted full step shorter than step_tolerance * (|x| + step_tolerance).
  The last four describe the undamped model only when the damping is small, so they count
  only while lambda <= `convergence_damping`: a heavily damped step is short and lowers the
  cost little wherever x is. After an accepted step whose model error |actual - predicted
  decrease| was below the cost tolerance, a problem with `gradient(x) -> (g, F)` is first asked
  for the new gradient alone (the kept Hessian then serves the decrement test) before new
  Hessians are paid for.
Otherwise the run ends unconverged: "max_iterations" (one iteration = one linear solve),
"damping limit", "time budget" (`time_budget_s` of wall time, checked between iterations; the
best x so far is returned) or "linear solver failed".
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from meshfg_ros.core.solvers.linear_solvers import LinearSolveError, LinearSolver, NotPositiveDefiniteError, make_linear_solver

# An accepted full step whose true decrease exceeds the model's by this factor is extended along
# its direction to the minimiser of the parabola through the costs (at most MAX_EXTRAPOLATION
# times the step); see _Run.extrapolate.
EXTRAPOLATION_GAIN = 1.2
MAX_EXTRAPOLATION = 4.0

__all__ = ["LevenbergMarquardtConfig", "LevenbergMarquardtResult", "NonFiniteCostError", "levenberg_marquardt"]


class NonFiniteCostError(ValueError):
    """The cost at the starting point is NaN or infinite: there is nothing to optimise from."""


@dataclass(frozen=True)
class LevenbergMarquardtConfig:
    """Settings of `levenberg_marquardt`; see the module doc."""

    max_iterations: int = 10
    initial_damping: float = 1e-4
    damping_mode: str = "marquardt"   # "marquardt": lambda * diag(H); "identity": lambda * I
    damping_floor: float = 1e-6
    max_damping: float = 1e12
    cost_tolerance: float = 1e-8
    absolute_cost_tolerance: float = 0.0
    step_tolerance: float = 1e-10
    gradient_tolerance: float = 1e-10
    convergence_damping: float = 1e-3
    time_budget_s: float | None = None

    def __post_init__(self):
        if self.damping_mode not in ("marquardt", "identity"):
            raise ValueError(f"damping_mode must be 'marquardt' or 'identity', got {self.damping_mode!r}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.time_budget_s is not None and not self.time_budget_s > 0.0:
            raise ValueError(f"time_budget_s must be > 0 or None, got {self.time_budget_s}")


@dataclass
class LevenbergMarquardtResult:
    """Outcome: x (best, finite), costs, iteration counts, convergence and diagnostics.

    cost_history[i]: cost after iteration i (cost_history[0] is the initial cost).
    shortened_steps: accepted or not, steps cut to a fraction to keep element volumes.
    extrapolated_steps: accepted steps lengthened along their direction (see _Run.extrapolate).
    """

    x: np.ndarray
    initial_cost: float
    final_cost: float
    iterations: int
    accepted_steps: int
    converged: bool
    reason: str
    cost_history: list = field(default_factory=list)
    solve_times_ms: list = field(default_factory=list)
    decrement_times_ms: list = field(default_factory=list)  # of the convergence tests' preconditioner applications
    not_positive_definite: int = 0
    shortened_steps: int = 0
    extrapolated_steps: int = 0
    messages: list = field(default_factory=list)

    def summary(self) -> str:
        """One line for status messages: steps accepted and why the run ended."""
        state = "converged" if self.converged else "not converged"
        # A run that starts at an optimum (a re-weighted run from the last one's) says so.
        where = " at its starting point" if self.converged and not self.iterations else ""
        text = f"{state} ({self.reason}){where}; {self.accepted_steps} of {self.iterations} steps accepted"
        if self.shortened_steps:
            text += f", {self.shortened_steps} shortened to keep element volumes"
        if self.extrapolated_steps:
            text += f", {self.extrapolated_steps} extrapolated"
        return text


@dataclass
class _Proposal:
    """A step cut to its feasible fraction, the model's decrease and (once judged) the trial."""

    step: np.ndarray
    fraction: float
    predicted: float
    cost_before: float
    trial: np.ndarray | None = None
    trial_cost: float = np.inf
    gain: float = -np.inf   # rho of the step as proposed (before any extrapolation)

    @property
    def actual(self) -> float:
        return np.nan if self.trial is None else self.cost_before - self.trial_cost


class _Run:
    """One Levenberg-Marquardt run: the iterate, its linearisation and the damping state."""

    def __init__(self, problem, x0: np.ndarray, config: LevenbergMarquardtConfig, solver: LinearSolver):
        self.problem, self.config, self.solver = problem, config, solver
        self.step_fraction = getattr(problem, "step_fraction", None)
        self.deadline = None if config.time_budget_s is None else time.perf_counter() + config.time_budget_s
        self.x = np.array(x0, dtype=np.float64)
        self.system, self.gradient, self.cost = problem.linearize(self.x)
        if not np.isfinite(self.cost):
            raise NonFiniteCostError(f"the cost at the starting point is {self.cost}")
        self.result = LevenbergMarquardtResult(self.x, self.cost, self.cost, 0, 0, False, "max_iterations",
                                               cost_history=[self.cost])
        self.initial_gradient = max(1.0, float(np.max(np.abs(self.gradient), initial=0.0)))
        self.damping, self.nu = config.initial_damping, 2.0
        if config.damping_mode == "identity":
            self.damping *= float(np.max(np.abs(self.system.diagonal()), initial=1.0))
        self.linearized = True      # system and gradient belong to x
        self.gradient_first = False  # the last step's model was accurate: try the gradient alone first
        self.fresh_hessian = True   # the decrement test has not yet seen this linearisation
        self._damped_kept = None    # (system, damping, damped system): see _damped

    # ------------------------------------------------------------------ the run
    def run(self) -> LevenbergMarquardtResult:
        """Iterate until x passes a convergence test, a limit is reached or an iteration ends
        the run (each step a (reason, converged) pair or None)."""
        stop = None
        while stop is None:
            stop = self.test_convergence() or self.limit_reached() or self.iterate()
        return self.finish(*stop)

    def iterate(self) -> tuple[str, bool] | None:
        """One iteration: propose a step, judge it, adapt the damping."""
        result = self.result
        result.iterations += 1
        try:
            proposal = self.propose()
        except LinearSolveError as error:
            result.messages.append(str(error))
            result.cost_history.append(self.cost)
            return "linear solver failed", False
        if proposal is not None and self.negligible(proposal):
            result.cost_history.append(self.cost)
            return "predicted decrease", True
        accepted = proposal is not None and self.judge(proposal)
        reason = self.converged_by_step(proposal) if accepted else None
        if accepted:
            self.accept(proposal)
        result.cost_history.append(self.cost)
        self.adapt_damping(proposal, accepted)
        if reason:
            return reason, True
        if not accepted and self.damping > self.config.max_damping:
            return "damping limit", False
        return None

    def test_convergence(self) -> tuple[str, bool] | None:
        """Whether x passes an optimality test, re-linearising first when x moved."""
        reason = None if self.linearized else self.relinearize()
        reason = reason or self.converged_here()
        return (reason, True) if reason else None

    def limit_reached(self) -> tuple[str, bool] | None:
        if self.result.iterations >= self.config.max_iterations:
            return "max_iterations", False
        if self.deadline is not None and time.perf_counter() > self.deadline:
            return "time budget", False
        return None

    def finish(self, reason: str, converged: bool) -> LevenbergMarquardtResult:
        result = self.result
        result.reason, result.converged = reason, converged
        result.x, result.final_cost = self.x, self.cost
        if result.not_positive_definite:
            result.messages.append(
                f"damped system not positive definite {result.not_positive_definite} time(s): damping raised"
            )
        return result

    # ------------------------------------------------------------------ propose
    def propose(self) -> _Proposal | None:
        """The damped Gauss-Newton step cut to its feasible fraction, or None when the damped
        system is not positive definite or the step is not finite."""
        try:
            step, stats = self.solver.solve(self._damped(self.damping), -self.gradient)
        except NotPositiveDefiniteError:
            self.result.not_positive_definite += 1
            return None
        self.result.solve_times_ms.append(stats.time_ms)
        if stats.message:
            self.result.messages.append(stats.message)
        return self.shorten(step) if np.all(np.isfinite(step)) else None

    def shorten(self, step: np.ndarray) -> _Proposal:
        """Cut the step to its feasible fractions; the model's decrease for what is left (exact
        for any scaling of the step's parts). The proposal's fraction is the smallest."""
        fractions = 1.0 if self.step_fraction is None else self.step_fraction(self.x, step)
        fraction = float(np.min(fractions))
        if fraction < 1.0:
            self.result.shortened_steps += 1
        scaled = fractions * step
        predicted = -float(self.gradient @ scaled) - 0.5 * float(scaled @ self.system.matvec(scaled))
        return _Proposal(scaled, fraction, predicted, self.cost)

    def _damped(self, damping: float):
        """The damped system at the current linearisation, one object per (linearisation,
        damping): the decrement test and the step that follows it hand the solver the same
        system, whose work on it (PCGSolver.decrement) the solve can then reuse."""
        kept = self._damped_kept
        if kept is None or kept[0] is not self.system or kept[1] != damping:
            kept = self._damped_kept = (self.system, damping,
                                        self.system.with_added_diagonal(damping * self._scaling(self.system)))
        return kept[2]

    def _scaling(self, system) -> np.ndarray:
        if self.config.damping_mode == "identity":
            return np.ones(system.size)
        diagonal = np.abs(system.diagonal())
        return np.maximum(diagonal, self.config.damping_floor * max(float(diagonal.mean()), 1e-300))

    def negligible(self, proposal: _Proposal) -> bool:
        """A full, lightly damped step whose predicted decrease is below the cost tolerance:
        x is optimal to that tolerance (the "predicted decrease" test)."""
        return (proposal.fraction == 1.0 and self.lightly_damped
                and 0.0 <= proposal.predicted <= self.tolerance(self.cost))

    # ------------------------------------------------------------------ judge
    def judge(self, proposal: _Proposal) -> bool:
        """Evaluate the trial's true cost; whether the step is accepted (positive gain ratio)."""
        if proposal.fraction > 0.0 and proposal.predicted > 0.0:
            trial = self.x + proposal.step
            trial_cost = float(self.problem.cost(trial))
            if np.isfinite(trial_cost):
                proposal.trial, proposal.trial_cost = trial, trial_cost
                proposal.gain = proposal.actual / proposal.predicted
        accepted = proposal.trial is not None and proposal.gain > 0.0
        if accepted and proposal.fraction == 1.0 and proposal.gain > EXTRAPOLATION_GAIN:
            self.extrapolate(proposal)
        return accepted

    def extrapolate(self, proposal: _Proposal) -> None:
        """Lengthen an accepted step whose true decrease beat the model's by far.

        The Gauss-Newton model then overestimates the curvature along the step (point-to-surface
        distances at an optimum that the prior holds off the data leave systematic residuals,
        whose second-order terms Gauss-Newton drops), and undamped steps stop short of the
        minimum: linear convergence. The parabola through F(x), the slope g.dx and F(x + dx)
        gives the minimiser alpha* along dx; x + alpha* dx (alpha* at most MAX_EXTRAPOLATION,
        within the step's feasible fraction) replaces the trial when its cost is lower."""
        slope = float(self.gradient @ proposal.step)
        curvature = 2.0 * (proposal.trial_cost - proposal.cost_before - slope)
        if not (slope < 0.0 and curvature > 0.0):
            return
        alpha = min(-slope / curvature, MAX_EXTRAPOLATION)
        if alpha <= 1.0 + 1e-3:
            return
        longer = alpha * proposal.step
        if self.step_fraction is not None and np.min(self.step_fraction(self.x, longer)) < 1.0:
            return
        trial = self.x + longer
        trial_cost = float(self.problem.cost(trial))
        if np.isfinite(trial_cost) and trial_cost < proposal.trial_cost:
            proposal.step, proposal.trial, proposal.trial_cost = longer, trial, trial_cost
            self.result.extrapolated_steps += 1

    def converged_by_step(self, proposal: _Proposal) -> str | None:
        """The convergence test an accepted step passes ("cost" or "step"), judged from the x
        it leaves; a shortened or heavily damped step passes none."""
        if proposal.fraction < 1.0 or not self.lightly_damped:
            return None
        if proposal.actual < self.tolerance(self.cost):
            return "cost"
        tolerance = self.config.step_tolerance
        if float(np.linalg.norm(proposal.step)) <= tolerance * (float(np.linalg.norm(self.x)) + tolerance):
            return "step"
        return None

    def accept(self, proposal: _Proposal) -> None:
        """Move to the trial. When the model predicted its decrease to within the cost
        tolerance, the next convergence test asks for the gradient alone first."""
        self.gradient_first = (hasattr(self.problem, "gradient") and proposal.gain <= EXTRAPOLATION_GAIN and
                               abs(proposal.actual - proposal.predicted) <= self.tolerance(proposal.trial_cost))
        self.x, self.cost = proposal.trial, proposal.trial_cost
        self.linearized = False
        self.result.accepted_steps += 1

    # ------------------------------------------------------------------ adapt the damping
    def adapt_damping(self, proposal: _Proposal | None, accepted: bool) -> None:
        if accepted:
            self.damping *= max(1.0 / 3.0, 1.0 - (2.0 * proposal.gain - 1.0) ** 3)
            self.nu = 2.0
            if proposal.fraction < 1.0:
                self.damping *= 2.0
        else:
            self.damping *= self.nu
            self.nu *= 2.0

    @property
    def lightly_damped(self) -> bool:
        """Whether the damped model is close enough to the undamped one for its small predicted
        decrease (or a small accepted decrease) to mean optimality."""
        if self.config.damping_mode == "identity":
            scale = float(np.max(np.abs(self.system.diagonal()), initial=1.0))
            return self.damping <= self.config.convergence_damping * scale
        return self.damping <= self.config.convergence_damping

    # ------------------------------------------------------------------ test convergence
    def tolerance(self, cost: float) -> float:
        """Cost changes below this do not matter: max(absolute, relative * cost)."""
        return max(self.config.absolute_cost_tolerance, self.config.cost_tolerance * cost)

    def converged_here(self) -> str | None:
        """The optimality test x passes with the current gradient and Hessians, or None."""
        if self.small_gradient():
            return "gradient"
        if self.fresh_hessian:
            self.fresh_hessian = False
            if self.small_decrement():
                return "decrement"
        return None

    def small_gradient(self) -> bool:
        return np.max(np.abs(self.gradient), initial=0.0) <= self.config.gradient_tolerance * self.initial_gradient

    def small_decrement(self) -> bool:
        """Newton decrement of the (floor-damped) model below the cost tolerance."""
        if not self.lightly_damped:
            return False
        start = time.perf_counter()
        try:
            estimate = self.solver.decrement(self._damped(self.damping), self.gradient)
        except (NotPositiveDefiniteError, LinearSolveError):
            return False
        finally:
            self.result.decrement_times_ms.append(1e3 * (time.perf_counter() - start))
        return 0.0 <= estimate <= self.tolerance(self.cost)

    def relinearize(self) -> str | None:
        """New Hessians at x, after a gradient-only convergence test where the last step's model
        was accurate; returns the test that passed, if one did."""
        if self.gradient_first:
            self.gradient, self.cost = self.problem.gradient(self.x)
            self.fresh_hessian = True
            reason = self.converged_here()
            if reason:
                return reason
        self.system, self.gradient, self.cost = self.problem.linearize(self.x)
        self.linearized, self.fresh_hessian = True, True
        return None


def levenberg_marquardt(problem, x0: np.ndarray, config: LevenbergMarquardtConfig | None = None,
                        solver: LinearSolver | None = None) -> LevenbergMarquardtResult:
    """Minimise problem's cost from x0.

    problem: linearize(x) -> (WindowSystem H, gradient, cost); cost(x) -> float;
    step_fraction(x, dx) -> float or array of dx's shape, in [0, 1] (optional: the largest
    fraction of dx, or of each of its unknowns, that keeps every element's volume above its
    margin); gradient(x) -> (gradient, cost) (optional: the
    same gradient and cost without Hessians). Raises NonFiniteCostError when the cost at x0 is
    not finite.
    """
    return _Run(problem, x0, config or LevenbergMarquardtConfig(), solver or make_linear_solver("pcg")).run()
