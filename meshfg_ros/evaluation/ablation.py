"""Factor ablation on the deforming cubes: the paper's Table I.

Each configuration runs the estimator over the same scenario through the nodes' step loop
(core/scheduler.py): the simulator predicts from each configuration's own previous estimate
(closed loop, as live); configurations without the physics prior start each state from the
copy-forward.
Vertex RMSE against the ground truth over all, external (surface) and unobserved external
vertices (surface vertices on no measured face), mean and std over steps, in millimetres.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

from meshfg_ros.core.estimation.estimator import EstimatorConfig
from meshfg_ros.core.scheduler import OfflinePipeline, run_offline
from meshfg_ros.evaluation.metrics import summarise, unobserved_external_vertices, vertex_rmse
from meshfg_ros.parameters import shared_settings
from meshfg_ros.synthetic.scenarios import Scenario, generate

ABLATION_CONFIGURATIONS = ("temporal", "measurement", "temporal+measurement", "simulation+measurement", "full")
VERTEX_SETS = ("all", "external", "unobserved_external")
PAPER_SHEAR_MM = {  # Table I of the paper, shear case: all / external / unobserved external
    "temporal": (5.5, 5.3, 5.3), "measurement": (280, 300, 350), "temporal+measurement": (120, 98, 110),
    "simulation+measurement": (0.73, 0.77, 0.67), "full": (0.73, 0.76, 0.67),
}
# The paper's ranking of the configurations by their error over all vertices, worst first; its
# last two tie (0.73 mm each), so they share the last place.
PAPER_RANKING = ("measurement", "temporal+measurement", "temporal")
PAPER_TIED_LAST = ("simulation+measurement", "full")


def estimator_config_for(scenario: Scenario, factors: str, **overrides) -> EstimatorConfig:
    """The estimator's nominal model for a scenario: the settings it shares with the simulator's
    (material, tool), its noise, its prior kind."""
    return EstimatorConfig(**{**shared_settings(scenario.simulator_config, EstimatorConfig), "factors": factors,
                              "measurement_sigma": scenario.noise_sigma_m, **scenario.estimator_overrides,
                              **overrides})


def run_configuration(scenario: Scenario, factors: str, progress: tqdm | None = None, **overrides) -> dict:
    """Estimate every step of `scenario` with one factor configuration through the nodes' step
    loop (core/scheduler.py); per-step RMSEs (m) of the steps that gave an estimate."""
    mesh = scenario.initial_mesh
    pipeline = OfflinePipeline(mesh, scenario.simulator_config, estimator_config_for(scenario, factors, **overrides),
                               scenario.grasped_vertices)
    truths = {step.stamp_ns: step.truth for step in scenario.steps}
    unobserved = unobserved_external_vertices(mesh.surface_vertices, mesh.surface_triangles,
                                              scenario.observed_triangles)
    vertex_sets = {"all": None, "external": mesh.surface_vertices, "unobserved_external": unobserved}
    errors = {name: [] for name in VERTEX_SETS}
    iterations = []
    for step in run_offline(pipeline, scenario.events()):
        iterations.append(step.result.iterations)
        for name, indices in vertex_sets.items():
            errors[name].append(vertex_rmse(step.result.positions, truths[step.stamp_ns], indices))
        if progress is not None:
            progress.update(1)
    return {"errors_m": errors, "iterations": iterations, "unobserved_external_count": int(len(unobserved))}


def run_ablation(scenario_name: str, steps: int = 15, seed: int = 0, progress: bool = True) -> dict:
    """Table I for one cube scenario, as the JSON structure of `meshfg ablation --json`."""
    scenario = generate(scenario_name, seed=seed, steps=steps)
    bar = tqdm(total=steps * len(ABLATION_CONFIGURATIONS), desc=f"ablation {scenario_name}", unit="step",
               file=sys.stderr, disable=not progress)
    configurations, iterations = {}, {}
    try:
        for factors in ABLATION_CONFIGURATIONS:
            bar.set_postfix_str(factors)
            run = run_configuration(scenario, factors, progress=bar)
            configurations[factors] = {
                name: dict(zip(("mean_mm", "std_mm"), (1e3 * v for v in summarise(values))))
                for name, values in run["errors_m"].items()
            }
            iterations[factors] = run["iterations"]
    finally:
        bar.close()
    return {
        "scenario": scenario_name, "noise_sigma_m": scenario.noise_sigma_m, "steps": steps, "seed": seed,
        "vertices": scenario.initial_mesh.vertex_count,
        "unobserved_external_vertices": run["unobserved_external_count"],
        "configurations": configurations, "lm_iterations": iterations,
    }


def format_table(result: dict) -> str:
    """Table I layout: configuration x (all, external, unobserved external), mean +/- std mm."""
    header = f"{'Factor configuration':<24}{'All':>18}{'External':>18}{'Unobserved ext.':>18}"
    lines = [f"Vertex RMSE (mm), {result['scenario']}, {result['steps']} steps, "
             f"noise sigma {result['noise_sigma_m'] * 1e3:g} mm, {result['vertices']} vertices "
             f"({result['unobserved_external_vertices']} unobserved external)", header, "-" * len(header)]
    for name in ABLATION_CONFIGURATIONS:
        row = result["configurations"][name]
        cells = "".join(f"{row[s]['mean_mm']:>10.3g} +/- {row[s]['std_mm']:<5.2g}" for s in VERTEX_SETS)
        lines.append(f"{name:<24}{cells}")
    if result["scenario"].startswith("cube-shear"):
        lines += ["", "The paper's Table I, shear case (mm)"]
        lines += [f"{name:<24}" + "".join(f"{value:>18g}" for value in PAPER_SHEAR_MM[name])
                  for name in ABLATION_CONFIGURATIONS]
    verdict = "holds" if paper_ranking_holds(result) else "does NOT hold"
    lines += ["", f"the paper's ranking over all vertices ({' > '.join(PAPER_RANKING)} > "
                  f"{' and '.join(PAPER_TIED_LAST)}): {verdict}"]
    return "\n".join(lines)


def paper_ranking_holds(result: dict) -> bool:
    """Whether the configurations' mean error over all vertices ranks as in the paper's Table I:
    PAPER_RANKING from the worst down, then both configurations with the simulation prior."""
    mean = {name: result["configurations"][name]["all"]["mean_mm"] for name in ABLATION_CONFIGURATIONS}
    ranked = [mean[name] for name in PAPER_RANKING] + [max(mean[name] for name in PAPER_TIED_LAST)]
    return all(worse > better for worse, better in zip(ranked, ranked[1:]))


def write_plot(result: dict, path) -> None:
    """Grouped bars (log scale): vertex RMSE per configuration and vertex set, with std."""
    from matplotlib.figure import Figure  # drawn by Agg, no pyplot state (as evaluation/render.py)

    fig = Figure(figsize=(9, 4))
    ax = fig.subplots()
    width = 0.8 / len(VERTEX_SETS)
    for offset, vertex_set in enumerate(VERTEX_SETS):
        rows = [result["configurations"][name][vertex_set] for name in ABLATION_CONFIGURATIONS]
        positions = [index + (offset - 1) * width for index in range(len(ABLATION_CONFIGURATIONS))]
        ax.bar(positions, [row["mean_mm"] for row in rows], width, yerr=[row["std_mm"] for row in rows],
               label=vertex_set.replace("_", " "), capsize=2)
    ax.set_xticks(range(len(ABLATION_CONFIGURATIONS)), ABLATION_CONFIGURATIONS, rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel("vertex RMSE (mm)")
    ax.set_title(f"{result['scenario']}: {result['steps']} steps, noise sigma {result['noise_sigma_m'] * 1e3:g} mm")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
