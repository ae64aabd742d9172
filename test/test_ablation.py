"""Table I ablation on a short deforming-cube run: the paper's ordering of configurations."""
import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest

from meshfg_ros.evaluation.ablation import (ABLATION_CONFIGURATIONS, PAPER_SHEAR_MM, VERTEX_SETS, format_table,
                                          paper_ranking_holds, run_ablation, write_plot)

MESHFG = Path(sys.executable).with_name("meshfg")


@pytest.fixture(scope="module")
def shear_table():
    return run_ablation("cube-shear-spd", steps=4, progress=False)


def test_simulation_prior_gives_sub_millimetre_errors(shear_table):
    rows = shear_table["configurations"]
    for name in ("simulation+measurement", "full"):
        for vertex_set in VERTEX_SETS:
            assert rows[name][vertex_set]["mean_mm"] <= 0.73, (name, vertex_set)


def test_configurations_order_as_in_the_paper(shear_table):
    mean = {name: shear_table["configurations"][name]["all"]["mean_mm"] for name in ABLATION_CONFIGURATIONS}
    worst_with_simulation = max(mean["simulation+measurement"], mean["full"])
    assert worst_with_simulation < mean["temporal"] < mean["measurement"]
    assert mean["measurement"] > mean["temporal+measurement"] > worst_with_simulation
    assert paper_ranking_holds(shear_table)
    assert "ranking over all vertices (measurement > temporal+measurement > temporal > " \
           "simulation+measurement and full): holds" in format_table(shear_table)


def test_a_ranking_unlike_the_paper_is_reported(shear_table):
    """temporal+measurement below temporal, as in no row of the paper: the verdict says so."""
    swapped = copy.deepcopy(shear_table)
    rows = swapped["configurations"]
    rows["temporal"]["all"]["mean_mm"] = 2.0 * rows["temporal+measurement"]["all"]["mean_mm"]
    assert not paper_ranking_holds(swapped)
    assert "does NOT hold" in format_table(swapped)


def test_table_and_json_layout(shear_table, tmp_path):
    text = format_table(shear_table)
    assert all(name in text for name in ABLATION_CONFIGURATIONS)
    assert "The paper's Table I, shear case (mm)" in text
    assert all(f"{PAPER_SHEAR_MM[name][0]:>18g}" in text for name in ABLATION_CONFIGURATIONS)
    assert set(shear_table["configurations"]) == set(ABLATION_CONFIGURATIONS)
    for row in shear_table["configurations"].values():
        assert set(row) == set(VERTEX_SETS)
        assert all(set(cell) == {"mean_mm", "std_mm"} for cell in row.values())
    assert shear_table["noise_sigma_m"] == pytest.approx(1e-3)
    assert shear_table["unobserved_external_vertices"] > 0
    write_plot(shear_table, tmp_path / "table.png")
    assert (tmp_path / "table.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # the meshfg command as a process
def test_ablation_command_refuses_to_overwrite(tmp_path):
    existing = tmp_path / "table.json"
    existing.write_text("{}")
    result = subprocess.run([str(MESHFG), "ablation", "--scenario", "cube-translate", "--steps", "2",
                             "--json", str(existing)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert "exists" in result.stderr and "Traceback" not in result.stderr
    assert json.loads(existing.read_text()) == {}
