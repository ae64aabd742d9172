"""blas.py: the BLAS CHOLMOD calls, chosen by the entry points for the CPU, never by an import.

Each case but the first runs in a fresh interpreter (marked slow): the binding happens once,
when cvxopt is first loaded.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from offline_helpers import mkl_installed

from meshfg_ros import blas

PROBE = """
import json, os, sys
import numpy as np, scipy.sparse
from threadpoolctl import threadpool_info
from meshfg_ros import blas
backend = blas.configure()
from meshfg_ros.core.physics.fem import ElasticModel
from meshfg_ros.synthetic.meshing import box_mesh
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky
mesh = box_mesh(1331, (0.1, 0.1, 0.1))  # big enough for supernodal CHOLMOD (BLAS calls)
matrix = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45).stiffness(kind="linear")
matrix = (matrix + 1e-2 * scipy.sparse.identity(matrix.shape[0])).tocsr()
rhs = np.sin(np.arange(matrix.shape[0]))
solution = SparseCholesky(matrix, node_size=3).solve(rhs)
sys.stdout.flush()
print("PROBE " + json.dumps({
    "backend": backend.name, "threads": backend.threads, "detail": backend.detail, "cpu": backend.cpu,
    "residual": float(np.linalg.norm(matrix @ solution - rhs) / np.linalg.norm(rhs)),
    "solution": solution.tolist(),
    "openblas_threads": [pool["num_threads"] for pool in threadpool_info() if pool["internal_api"] == "openblas"
                         and "cvxopt" not in pool["filepath"]],
    "mkl_threads": [pool["num_threads"] for pool in threadpool_info() if pool["internal_api"] == "mkl"],
    "mkl_layers": [pool.get("threading_layer") for pool in threadpool_info() if pool["internal_api"] == "mkl"],
    "layer_variable": os.environ.get("MKL_THREADING_LAYER"),
}))
"""

# Imports the whole core and factors with it, without an entry point, with MESHFG_BLAS=mkl set.
IMPORT_ONLY = """
import json, pkgutil, importlib
import numpy as np, scipy.linalg, scipy.sparse
from threadpoolctl import threadpool_info
import meshfg_ros.core
before = [(pool["filepath"], pool["num_threads"]) for pool in threadpool_info()]
for module in pkgutil.walk_packages(meshfg_ros.core.__path__, prefix="meshfg_ros.core."):
    importlib.import_module(module.name)
from meshfg_ros import blas
from meshfg_ros.core.solvers.sparse_cholesky import SparseCholesky
matrix = scipy.sparse.diags(np.arange(1.0, 2001.0)).tocsr()
solution = SparseCholesky(matrix).solve(np.ones(2000))
after = [(pool["filepath"], pool["num_threads"]) for pool in threadpool_info()]
print(json.dumps({"mkl_loaded": "libmkl_rt" in open("/proc/self/maps").read(),
                  "openblas_before": sorted(p for p in before if "openblas" in p[0]),
                  "openblas_after": sorted(p for p in after if "openblas" in p[0] and "cvxopt" not in p[0]),
                  "backend": blas.backend().name, "detail": blas.backend().detail,
                  "error": float(np.abs(solution * np.arange(1.0, 2001.0) - 1.0).max())}))
"""

# Calls one entry point, then says whether MKL was loaded. Each entry point fails fast here:
# `meshfg eval` of a missing recording, run_nodes with a node that cannot be made, the bench's
# machine() (what every bench section calls first).
ENTRY_POINTS = {
    "meshfg": "from meshfg_ros.cli import main\ncode = main(['eval', '/nonexistent', '--truth', '/nonexistent'])\n"
              "assert code == 1, code",
    "nodes": "from meshfg_ros.nodes.runtime import run_nodes\n"
             "def interrupted():\n    raise KeyboardInterrupt\n"
             "assert run_nodes('probe', [interrupted], args=['probe']) == 0",
    "bench": "from meshfg_ros.benchmarks.bench import machine\nmachine()",
}
AFTER_ENTRY = ("\nimport json\nfrom meshfg_ros import blas\n"
               "print(json.dumps({'mkl_loaded': 'libmkl_rt' in open('/proc/self/maps').read(), "
               "'backend': blas.backend().name}))")


def run_python(code: str, **environment) -> subprocess.CompletedProcess:
    env = {key: value for key, value in os.environ.items()
           if key not in ("MESHFG_BLAS", "MKL_THREADING_LAYER", "MKL_NUM_THREADS")}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                            env={**env, **environment})
    assert result.returncode == 0, result.stderr[-2000:]
    return result


def run_probe(**environment) -> dict:
    lines = run_python(PROBE, MKL_VERBOSE="1", **environment).stdout.splitlines()
    probe = json.loads(next(line for line in lines if line.startswith("PROBE "))[len("PROBE "):])
    probe["mkl_calls"] = [line.split()[1].split("(")[0] for line in lines if line.startswith("MKL_VERBOSE D")]
    return probe


@pytest.fixture(scope="module")
def bundled():
    return run_probe(MESHFG_BLAS="bundled")


def test_choice_follows_the_cpu_vendor_unless_set():
    assert blas.choose("GenuineIntel", None) == "mkl"
    assert blas.choose("AuthenticAMD", None) == "bundled"
    assert blas.choose("", None) == "bundled"  # no /proc/cpuinfo, or another architecture
    assert blas.choose("AuthenticAMD", "mkl") == "mkl"
    assert blas.choose("GenuineIntel", "bundled") == "bundled"
    with pytest.raises(blas.BlasSettingError, match="MESHFG_BLAS='openblas'"):
        blas.choose("GenuineIntel", "openblas")


def test_cpu_model_names_the_family_and_model_that_a_bare_name_hides(monkeypatch):
    cpuinfo = {"model name": "AMD EPYC", "cpu family": "26", "model": "2"}
    monkeypatch.setattr(blas, "_cpuinfo_field", cpuinfo.get)
    cores = len(os.sched_getaffinity(0))
    assert blas.cpu_model() == f"AMD EPYC (family 26, model 2), {cores} cores"
    cpuinfo.pop("cpu family")  # a CPU (or an OS) that gives no family: the name alone
    assert blas.cpu_model() == f"AMD EPYC, {cores} cores"


@pytest.mark.slow
def test_bundled_blas_solves_without_mkl(bundled):
    assert bundled["backend"] == "bundled" and bundled["detail"].startswith("MESHFG_BLAS=bundled")
    assert bundled["mkl_calls"] == []  # MKL was never called
    assert bundled["mkl_threads"] == []  # nor loaded
    assert bundled["residual"] < 1e-10


@pytest.mark.slow
def test_default_is_the_choice_for_this_cpu():
    probe = run_probe()
    expected = blas.choose(blas.cpu_vendor(), None)
    if expected == "mkl" and not mkl_installed():
        expected = "bundled"
    assert probe["backend"] == expected, probe["detail"]
    assert probe["cpu"] == blas.cpu_model() and blas.cpu_vendor() in probe["detail"]
    assert probe["residual"] < 1e-10
    assert probe["openblas_threads"] and set(probe["openblas_threads"]) == {1}  # no spinning pools
    # One BLAS thread unless MKL_NUM_THREADS asks for more: fair to the other processes' cores.
    assert probe["threads"] == 1 and set(probe["mkl_threads"]) <= {1}


@pytest.mark.slow
@pytest.mark.skipif(not mkl_installed(), reason="the mkl package is not installed (x86-64 Linux only)")
def test_cholmod_calls_threaded_mkl_and_agrees_with_its_own_blas(bundled):
    probe = run_probe(MESHFG_BLAS="mkl", MKL_NUM_THREADS="2")
    assert probe["backend"] == "mkl", probe["detail"]
    assert probe["threads"] == 2 and probe["mkl_threads"] == [2]  # what MKL itself reports
    # CHOLMOD's supernodal factorisation and solve went through MKL (its verbose log names them).
    assert {"DPOTRF", "DSYRK", "DGEMM", "DTRSM"} <= set(probe["mkl_calls"]), sorted(set(probe["mkl_calls"]))
    assert probe["residual"] < 1e-10
    reference = np.asarray(bundled["solution"])
    np.testing.assert_allclose(probe["solution"], reference, rtol=0.0, atol=1e-10 * np.abs(reference).max())
    assert probe["openblas_threads"] and set(probe["openblas_threads"]) == {1}  # no pools spinning against MKL's
    # On torch's GNU OpenMP, chosen through MKL's API: children do not inherit a layer setting.
    assert probe["mkl_layers"] == ["gnu"] and probe["layer_variable"] is None


@pytest.mark.slow
def test_importing_the_core_binds_nothing_and_changes_no_threading():
    """Without an entry point, even with MESHFG_BLAS=mkl, the core leaves MKL unloaded and
    numpy's and scipy's pools as they were; CHOLMOD runs on cvxopt's own BLAS and says so."""
    result = json.loads(run_python(IMPORT_ONLY, MESHFG_BLAS="mkl").stdout)
    assert result["mkl_loaded"] is False
    assert result["openblas_before"] and result["openblas_after"] == result["openblas_before"]
    assert result["backend"] == "bundled" and "configure() was not called" in result["detail"]
    assert result["error"] < 1e-12


@pytest.mark.slow
@pytest.mark.skipif(not mkl_installed(), reason="the mkl package is not installed (x86-64 Linux only)")
@pytest.mark.parametrize("entry_point", sorted(ENTRY_POINTS))
def test_each_entry_point_binds_the_blas(entry_point):
    result = json.loads(run_python(ENTRY_POINTS[entry_point] + AFTER_ENTRY, MESHFG_BLAS="mkl").stdout.splitlines()[-1])
    assert result == {"mkl_loaded": True, "backend": "mkl"}


@pytest.mark.slow
@pytest.mark.skipif(not mkl_installed(), reason="the mkl package is not installed (x86-64 Linux only)")
def test_binding_after_cvxopt_was_loaded_is_refused_and_says_so():
    code = ("import cvxopt.cholmod\nfrom meshfg_ros import blas\n"
            "backend = blas.configure()\nprint(backend.name + '|' + backend.detail)")
    output = run_python(code, MESHFG_BLAS="mkl").stdout.strip()
    assert output == "bundled|MESHFG_BLAS=mkl, but cvxopt was imported before MKL could be bound"


@pytest.mark.slow
def test_an_unknown_setting_is_a_one_line_error():
    env = {key: value for key, value in os.environ.items() if key != "MESHFG_BLAS"}
    result = subprocess.run([sys.executable, "-m", "meshfg_ros.cli", "eval", "x", "--truth", "y"], capture_output=True,
                            text=True, timeout=120, env={**env, "MESHFG_BLAS": "openblas"})
    assert result.returncode == 1
    assert result.stderr.strip() == "meshfg eval: error: MESHFG_BLAS='openblas': expected one of mkl, bundled"
