"""blas.py: CHOLMOD's BLAS calls bound to threaded MKL (when installed), same answers as cvxopt's own.

Each case runs in a fresh interpreter: the binding happens once, when cvxopt is first loaded.
"""

import importlib.metadata
import json
import os
import subprocess
import sys

import numpy as np
import pytest

PROBE = """
import json, os, sys
import numpy as np, scipy.sparse
from threadpoolctl import threadpool_info
from meshfg_ros.core.fem import ElasticModel
from meshfg_ros.core.meshing import box_mesh
from meshfg_ros.core.sparse_cholesky import BLAS_BACKEND, SparseCholesky
mesh = box_mesh(1331, (0.1, 0.1, 0.1))  # big enough for supernodal CHOLMOD (BLAS calls)
matrix = ElasticModel(mesh.vertices, mesh.tetrahedra, 3e3, 0.45).stiffness(kind="linear")
matrix = (matrix + 1e-2 * scipy.sparse.identity(matrix.shape[0])).tocsr()
rhs = np.sin(np.arange(matrix.shape[0]))
solution = SparseCholesky(matrix, node_size=3).solve(rhs)
sys.stdout.flush()
print("PROBE " + json.dumps({
    "backend": BLAS_BACKEND.name, "threads": BLAS_BACKEND.threads, "detail": BLAS_BACKEND.detail,
    "residual": float(np.linalg.norm(matrix @ solution - rhs) / np.linalg.norm(rhs)),
    "solution": solution.tolist(),
    "openblas_threads": [pool["num_threads"] for pool in threadpool_info() if pool["internal_api"] == "openblas"],
    "mkl_layers": [pool.get("threading_layer") for pool in threadpool_info() if pool["internal_api"] == "mkl"],
    "layer_variable": os.environ.get("MKL_THREADING_LAYER"),
}))
"""


def run_probe(**environment):
    env = {key: value for key, value in os.environ.items() if key not in ("MESHFG_BLAS", "MKL_THREADING_LAYER")}
    env.update(MKL_VERBOSE="1", **environment)
    result = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    lines = result.stdout.splitlines()
    probe = json.loads(next(line for line in lines if line.startswith("PROBE "))[len("PROBE "):])
    probe["mkl_calls"] = [line.split()[1].split("(")[0] for line in lines if line.startswith("MKL_VERBOSE D")]
    return probe


def mkl_installed() -> bool:
    try:
        importlib.metadata.distribution("mkl")
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


@pytest.fixture(scope="module")
def bundled():
    return run_probe(MESHFG_BLAS="bundled")


def test_bundled_blas_solves_without_mkl(bundled):
    assert bundled["backend"] == "bundled" and bundled["detail"] == "MESHFG_BLAS=bundled"
    assert bundled["mkl_calls"] == []  # MKL was never called
    assert bundled["residual"] < 1e-10


@pytest.mark.skipif(not mkl_installed(), reason="the mkl package is not installed (x86-64 Linux only)")
def test_cholmod_calls_threaded_mkl_and_agrees_with_its_own_blas(bundled):
    probe = run_probe()
    assert probe["backend"] == "mkl", probe["detail"]
    assert probe["threads"] == len(os.sched_getaffinity(0))
    # CHOLMOD's supernodal factorisation and solve went through MKL (its verbose log names them).
    assert {"DPOTRF", "DSYRK", "DGEMM", "DTRSM"} <= set(probe["mkl_calls"]), sorted(set(probe["mkl_calls"]))
    assert probe["residual"] < 1e-10
    reference = np.asarray(bundled["solution"])
    np.testing.assert_allclose(probe["solution"], reference, rtol=0.0, atol=1e-10 * np.abs(reference).max())
    assert probe["openblas_threads"] and set(probe["openblas_threads"]) == {1}  # no pools spinning against MKL's
    # On torch's GNU OpenMP, chosen through MKL's API: children do not inherit a layer setting.
    assert probe["mkl_layers"] == ["gnu"] and probe["layer_variable"] is None


def test_binding_after_cvxopt_was_loaded_is_refused_and_says_so():
    code = ("import cvxopt.cholmod\nfrom meshfg_ros.core.blas import bind_threaded_blas\n"
            "backend = bind_threaded_blas()\nprint(backend.name + '|' + backend.detail)")
    env = {key: value for key, value in os.environ.items() if key != "MESHFG_BLAS"}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "bundled|cvxopt was imported before MKL could be bound"
