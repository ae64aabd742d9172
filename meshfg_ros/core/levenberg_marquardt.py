"""Levenberg-Marquardt on sparse normal equations (Nielsen's damping update).

The problem gives, at x, the Gauss-Newton system H (a WindowSystem), the gradient g = J^T W r
and the cost F = 0.5 r^T W r; each iteration solves (H + lambda D) dx = -g with D = diag(H)
(Marquardt; clamped below by `damping_floor` * mean |diag H| so unconstrained coordinates
still get damped) or D = I, and accepts the step when the gain ratio
    rho = (F(x) - F(x + dx)) / (L(0) - L(dx)),  L(0) - L(dx) = -g.dx - 0.5 dx.H dx
is positive; then lambda *= max(1/3, 1 - (2 rho - 1)^3) and nu = 2, else lambda *= nu and
nu *= 2 (Nielsen 1999 / Madsen-Nielsen-Tingleff). H may be indefinite (the paper's raw
Neo-Hookean prior): a damped system that is not positive definite (Cholesky or PCG reports
it) or a step whose predicted decrease is not positive is a failed step that raises lambda,
so the accepted steps are those of a positive definite damped model. A step that would invert
a tetrahedron (problem.acceptable) fails the same way.

Termination (converged=True): relative cost decrease of an accepted step below
`cost_tolerance` (or a step whose predicted decrease is below it: even its success would
end the run; after an accepted step that predicted decrease is first estimated without a
solve, solver.decrement: 0.5 g^T M^-1 g with PCG's preconditioner M, and a small estimate
ends the run before the solve, reason "decrement"; when the accepted step's model error
|actual - predicted decrease| was itself below the cost tolerance, the run has probably
converged, and a problem with `gradient(x) -> (g, F)` is asked for the new gradient alone,
tested with the kept Hessian before new Hessians are paid for), step norm below
`step_tolerance` * (|x| + step_tolerance), or |g|_inf below `gradient_tolerance` *
max(1, |g_0|_inf); otherwise max_iterations (one iteration = one linear solve) or lambda
above `max_damping` end it unconverged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .linear_solvers import LinearSolveError, LinearSolver, NotPositiveDefiniteError, make_linear_solver

__all__ = ["LevenbergMarquardtConfig", "LevenbergMarquardtResult", "levenberg_marquardt"]


@dataclass(frozen=True)
class LevenbergMarquardtConfig:
    """Settings of `levenberg_marquardt`; see the module doc."""

    max_iterations: int = 10
    initial_damping: float = 1e-4
    damping_mode: str = "marquardt"   # "marquardt": lambda * diag(H); "identity": lambda * I
    damping_floor: float = 1e-6
    max_damping: float = 1e12
    cost_tolerance: float = 1e-8
    step_tolerance: float = 1e-10
    gradient_tolerance: float = 1e-10

    def __post_init__(self):
        if self.damping_mode not in ("marquardt", "identity"):
            raise ValueError(f"damping_mode must be 'marquardt' or 'identity', got {self.damping_mode!r}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")


@dataclass
class LevenbergMarquardtResult:
    """Outcome: x (best, finite), costs, iteration counts, convergence and diagnostics.

    cost_history[i]: cost after iteration i (cost_history[0] is the initial cost).
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
    not_positive_definite: int = 0
    inverting_steps: int = 0
    messages: list = field(default_factory=list)


def levenberg_marquardt(problem, x0: np.ndarray, config: LevenbergMarquardtConfig | None = None,
                        solver: LinearSolver | None = None) -> LevenbergMarquardtResult:
    """Minimise problem's cost from x0.

    problem: linearize(x) -> (WindowSystem H, gradient, cost); cost(x) -> float;
    acceptable(x) -> bool (optional: no inverted elements); gradient(x) -> (gradient, cost)
    (optional: the same gradient and cost without Hessians).
    """
    config = config or LevenbergMarquardtConfig()
    solver = solver or make_linear_solver("pcg")
    acceptable = getattr(problem, "acceptable", lambda x: True)
    x = np.array(x0, dtype=np.float64)
    system, gradient, cost = problem.linearize(x)
    if not np.isfinite(cost):
        raise ValueError("initial cost is not finite")
    result = LevenbergMarquardtResult(x, cost, cost, 0, 0, False, "max_iterations", cost_history=[cost])
    initial_gradient = max(1.0, float(np.max(np.abs(gradient), initial=0.0)))
    damping, nu = config.initial_damping, 2.0
    if config.damping_mode == "identity":
        damping *= float(np.max(np.abs(system.diagonal())))

    def damped_system(system, damping):
        if config.damping_mode == "marquardt":
            diagonal = np.abs(system.diagonal())
            scaling = np.maximum(diagonal, config.damping_floor * max(float(diagonal.mean()), 1e-300))
        else:
            scaling = np.ones(system.size)
        return system.with_added_diagonal(damping * scaling)

    def small_decrement(damped, gradient, cost) -> bool:
        try:
            estimate = solver.decrement(damped, gradient)
        except (NotPositiveDefiniteError, LinearSolveError):
            return False
        return 0.0 <= estimate <= config.cost_tolerance * cost

    def small_gradient(gradient) -> bool:
        return np.max(np.abs(gradient), initial=0.0) <= config.gradient_tolerance * initial_gradient

    linearized, moved, gradient_first = True, False, False
    while result.iterations < config.max_iterations:
        if not linearized:
            if gradient_first:
                # The last step's model error was below the tolerance: probably converged.
                # Test with the new gradient and the kept Hessian before paying for new ones.
                gradient, cost = problem.gradient(x)
                if small_gradient(gradient):
                    result.converged, result.reason = True, "gradient"
                    break
                if small_decrement(damped_system(system, damping), gradient, cost):
                    result.converged, result.reason = True, "decrement"
                    break
            system, gradient, cost = problem.linearize(x)
            # (moved: test the decrement again with the new Hessians, which estimate it better)
            linearized, moved = True, True
        if small_gradient(gradient):
            result.converged, result.reason = True, "gradient"
            break
        damped = damped_system(system, damping)
        if moved:
            moved = False
            if small_decrement(damped, gradient, cost):
                result.converged, result.reason = True, "decrement"
                break
        result.iterations += 1
        try:
            step, stats = solver.solve(damped, -gradient)
            result.solve_times_ms.append(stats.time_ms)
            if stats.message:
                result.messages.append(stats.message)
        except NotPositiveDefiniteError:
            result.not_positive_definite += 1
            step = None
        except LinearSolveError as error:
            result.messages.append(str(error))
            result.reason = "linear solver failed"
            result.cost_history.append(cost)
            break
        accepted = False
        if step is not None and np.all(np.isfinite(step)):
            predicted = -float(gradient @ step) - 0.5 * float(step @ system.matvec(step))
            if 0.0 <= predicted <= config.cost_tolerance * cost:
                result.cost_history.append(cost)
                result.converged, result.reason = True, "predicted decrease"
                break
            trial = x + step
            if predicted > 0.0 and acceptable(trial):
                trial_cost = problem.cost(trial)
                gain = (cost - trial_cost) / predicted
                if np.isfinite(trial_cost) and gain > 0.0:
                    accepted = True
                    gradient_first = (hasattr(problem, "gradient") and
                                      abs(cost - trial_cost - predicted) <= config.cost_tolerance * trial_cost)
                    relative_decrease = (cost - trial_cost) / max(cost, 1e-300)
                    step_norm, x_norm = float(np.linalg.norm(step)), float(np.linalg.norm(x))
                    x, cost = trial, trial_cost
                    linearized = False
                    result.accepted_steps += 1
                    damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                    nu = 2.0
            elif predicted > 0.0:
                result.inverting_steps += 1
        result.cost_history.append(cost)
        if accepted:
            if relative_decrease < config.cost_tolerance:
                result.converged, result.reason = True, "cost"
                break
            if step_norm <= config.step_tolerance * (x_norm + config.step_tolerance):
                result.converged, result.reason = True, "step"
                break
        else:
            damping *= nu
            nu *= 2.0
            if damping > config.max_damping:
                result.reason = "damping limit"
                break
    result.x, result.final_cost = x, cost
    if result.not_positive_definite:
        result.messages.append(
            f"damped system not positive definite {result.not_positive_definite} time(s): damping raised"
        )
    if result.inverting_steps:
        result.messages.append(f"{result.inverting_steps} step(s) rejected for inverting tetrahedra")
    return result

