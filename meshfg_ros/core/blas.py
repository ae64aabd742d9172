"""Multi-threaded BLAS for CHOLMOD: MKL bound in place of cvxopt's single-threaded OpenBLAS.

cvxopt's wheels link CHOLMOD against a bundled OpenBLAS 0.3.15 built single-threaded
(`openblas_get_config`: SINGLE_THREADED), and no other CHOLMOD wheel exists for this Python
(scikit-sparse has none), so a factorisation used one core. CHOLMOD's supernodal numeric
factorisation and its solves spend their time in six BLAS/LAPACK routines (dgemm_, dsyrk_,
dtrsm_, dpotrf_, dgemv_, dtrsv_) that the dynamic loader binds when cvxopt's modules are
loaded, looking in the process's global scope first. Loading MKL's single dynamic library
(`libmkl_rt`, from the `mkl` wheel) with RTLD_GLOBAL before cvxopt is imported therefore binds
them to MKL, threaded. No library does this swap, hence this module.

- MKL runs on the GNU OpenMP runtime that torch ships (loaded here by path, without importing
  torch), so a process that also uses torch has one OpenMP runtime, not two.
- The process's OpenBLAS pools (numpy's, scipy's) are held to one thread while MKL is bound:
  their threads, woken by PCG's long dot products, spin after each call and took the cores from
  MKL's (the organ-scale preconditioner application 139 ms against 70 ms).

Measured on this 2-core machine, organ-scale state block (31,944 dofs, METIS ordering):
numeric factorisation 0.50 s (cvxopt's OpenBLAS) against 0.36 s (MKL, 1 thread) and 0.26 s
(MKL, 2 threads); one solve 20.8 ms against 17.2 and 11.7 ms. In the organ-scale window update
(W=5, 20k points) the median went from 1.25 s to 0.88-0.92 s.

`MESHFG_BLAS=bundled` keeps cvxopt's own BLAS; MKL_NUM_THREADS and MKL_THREADING_LAYER are
honoured when set.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import importlib.util
import os
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["BlasBackend", "bind_threaded_blas"]


@dataclass(frozen=True)
class BlasBackend:
    """Which BLAS CHOLMOD calls: name ("mkl" or "bundled"), its threads, and why."""

    name: str
    threads: int
    detail: str


_backend: BlasBackend | None = None
_MKL_THREADING_LAYERS = {"INTEL": 0, "GNU": 3}  # MKL_THREADING_INTEL, MKL_THREADING_GNU (mkl_service.h)


def _mkl_runtime() -> Path | None:
    """libmkl_rt from the installed `mkl` distribution (pip puts it in <prefix>/lib)."""
    try:
        files = importlib.metadata.files("mkl") or []
    except importlib.metadata.PackageNotFoundError:
        return None
    for file in files:
        if file.name.startswith("libmkl_rt.so"):
            path = Path(file.locate()).resolve()
            if path.exists():
                return path
    return None


def _torch_openmp() -> Path | None:
    """The GNU OpenMP runtime bundled with torch (torch/lib/libgomp.so.1), found without importing torch."""
    spec = importlib.util.find_spec("torch")
    for location in (spec.submodule_search_locations or []) if spec else []:
        candidate = Path(location) / "lib" / "libgomp.so.1"
        if candidate.exists():
            return candidate
    return None


def _limit_openblas_pools() -> None:
    import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS, so that its pool is limited too)
    from threadpoolctl import ThreadpoolController

    ThreadpoolController().select(internal_api="openblas").limit(limits=1)


def bind_threaded_blas() -> BlasBackend:
    """Bind CHOLMOD's BLAS to threaded MKL when it is installed; call before cvxopt is imported.
    Idempotent; returns the backend in use."""
    global _backend
    if _backend is not None:
        return _backend
    if os.environ.get("MESHFG_BLAS", "mkl") == "bundled":
        _backend = BlasBackend("bundled", 1, "MESHFG_BLAS=bundled")
        return _backend
    if "cvxopt.cholmod" in sys.modules:
        _backend = BlasBackend("bundled", 1, "cvxopt was imported before MKL could be bound")
        return _backend
    runtime = _mkl_runtime()
    if runtime is None:
        _backend = BlasBackend("bundled", 1, "the mkl package is not installed")
        return _backend
    # The layer is set through MKL's API, not the environment, which child processes inherit.
    layer = os.environ.get("MKL_THREADING_LAYER", "").upper()
    openmp = _torch_openmp() if layer in ("", "GNU") else None
    if openmp is not None:
        ctypes.CDLL(str(openmp), mode=ctypes.RTLD_GLOBAL)  # libgomp.so.1, found by MKL's GNU layer
    try:
        mkl = ctypes.CDLL(str(runtime), mode=ctypes.RTLD_GLOBAL)
    except OSError as error:
        _backend = BlasBackend("bundled", 1, f"loading {runtime.name} failed: {error}")
        return _backend
    if not layer:
        layer = "GNU" if openmp is not None else "INTEL"  # INTEL: the mkl wheel's own libiomp5
        mkl.MKL_Set_Threading_Layer(ctypes.c_int(_MKL_THREADING_LAYERS[layer]))
    if "MKL_NUM_THREADS" not in os.environ:
        mkl.MKL_Set_Num_Threads(ctypes.c_int(len(os.sched_getaffinity(0))))
    threads = int(mkl.MKL_Get_Max_Threads())
    _limit_openblas_pools()
    _backend = BlasBackend("mkl", threads, f"{runtime}, {layer} threading")
    return _backend
