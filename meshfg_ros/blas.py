"""CHOLMOD's BLAS, chosen for the CPU at hand by the programs' entry points (`configure`).

cvxopt's wheels link CHOLMOD against a bundled OpenBLAS 0.3.15 built single-threaded
(`openblas_get_config`: SINGLE_THREADED), and no other CHOLMOD wheel exists for this Python
(scikit-sparse has none). CHOLMOD's supernodal numeric factorisation and its solves spend their
time in six BLAS/LAPACK routines (dgemm_, dsyrk_, dtrsm_, dpotrf_, dgemv_, dtrsv_) that the
dynamic loader binds when cvxopt's modules are loaded, looking in the process's global scope
first. Loading MKL's single dynamic library (`libmkl_rt`, from the `mkl` wheel) with
RTLD_GLOBAL before cvxopt is imported therefore binds them to MKL, threaded. No library does
this swap, hence this module.

Configuring is a choice for the whole process: it may load MKL and an OpenMP runtime, and it
holds numpy's and scipy's OpenBLAS pools to one thread. Importing meshfg_ros (the core included)
therefore changes nothing: the entry points (the `meshfg` command, the simulation and
estimator executables through nodes/runtime.py, `meshfg bench`, the test session's conftest)
call `configure()` before anything loads cvxopt (sparse_cholesky.py imports it on first use).
A process that loads cvxopt without calling it runs CHOLMOD on cvxopt's own BLAS, and
`backend()` says so.

What `configure()` binds: `MESHFG_BLAS` (`mkl` or `bundled`) when set; otherwise MKL on Intel
CPUs and cvxopt's bundled OpenBLAS on every other CPU (vendor_id in /proc/cpuinfo). On the
project's 2-core Intel VMs MKL's kernels factor and solve the organ-scale blocks faster than the
bundled OpenBLAS 0.3.15; on its AMD EPYC VMs MKL takes no AVX code path and the bundled
OpenBLAS's Zen kernels are the faster ones (measurements: docs/design-notes.md, "CHOLMOD's BLAS").

One BLAS thread, always, unless MKL_NUM_THREADS says otherwise (coarse pieces of work, each a
whole CHOLMOD solve or sparse product, are split over threads by core/worker_threads.py). The robot's computer shares its cores
with perception, planning and control, and the two nodes of this package are two processes. A
threaded BLAS makes every supernode a parallel region that waits for all its threads: with
another process on a core, each region waits for that core's time slice (or spins for it), and
an update that should take twice as long with half the CPU takes 4-7 times as long (MKL, two
threads, one busy process per core). A single thread slows in proportion to the CPU it gets.
Where the cores are the estimator's alone, MKL_NUM_THREADS=2 factors faster; see the README.
MKL_THREADING_LAYER is honoured when set. MKL runs on the GNU OpenMP runtime that torch ships
(loaded here by path, without importing torch), so a process that also uses torch has one
OpenMP runtime, not two. With either backend the process's OpenBLAS pools (numpy's, scipy's)
are held to one thread for the same reason: their threads spin after each call.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import importlib.util
import os
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["BlasBackend", "BlasSettingError", "backend", "choose", "configure", "cpu_model", "cpu_vendor"]

CHOICES = ("mkl", "bundled")
_MKL_THREADING_LAYERS = {"INTEL": 0, "GNU": 3}  # MKL_THREADING_INTEL, MKL_THREADING_GNU (mkl_service.h)


class BlasSettingError(ValueError):
    """MESHFG_BLAS names no known BLAS."""


@dataclass(frozen=True)
class BlasBackend:
    """Which BLAS CHOLMOD calls: name ("mkl" or "bundled"), its threads, why, and the CPU."""

    name: str
    threads: int
    detail: str
    cpu: str


_backend: BlasBackend | None = None


def _cpuinfo_field(name: str) -> str | None:
    """The first `name : value` of /proc/cpuinfo (None where there is none, e.g. not Linux)."""
    try:
        with open("/proc/cpuinfo") as stream:
            for line in stream:
                key, _, value = line.partition(":")
                if key.strip() == name:
                    return value.strip()
    except OSError:
        return None
    return None


def cpu_vendor() -> str:
    """The CPU vendor as the CPU names itself (GenuineIntel, AuthenticAMD, ...); "" if unknown."""
    return _cpuinfo_field("vendor_id") or ""


def cpu_model() -> str:
    """The CPU model name, its family and model numbers where the CPU gives them, and the number
    of cores this process may run on. A virtual machine may show a bare name ("AMD EPYC") for
    CPUs of several generations, which the family and model tell apart."""
    name = _cpuinfo_field("model name") or platform.processor() or platform.machine() or "unknown CPU"
    family, model = _cpuinfo_field("cpu family"), _cpuinfo_field("model")
    generation = f" (family {family}, model {model})" if family and model else ""
    return f"{name}{generation}, {len(os.sched_getaffinity(0))} cores"


def choose(vendor: str, setting: str | None) -> str:
    """The BLAS to bind: `setting` (MESHFG_BLAS) when given, else MKL on Intel CPUs only (module docstring)."""
    if setting:
        if setting not in CHOICES:
            raise BlasSettingError(f"MESHFG_BLAS={setting!r}: expected one of {', '.join(CHOICES)}")
        return setting
    return "mkl" if vendor == "GenuineIntel" else "bundled"


def backend() -> BlasBackend:
    """The BLAS CHOLMOD calls in this process: `configure()`'s choice, or cvxopt's own without it."""
    if _backend is not None:
        return _backend
    return BlasBackend("bundled", 1, "configure() was not called: cvxopt's own", cpu_model())


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


def _bind_mkl(cpu: str, reason: str) -> BlasBackend:
    runtime = _mkl_runtime()
    if runtime is None:
        return BlasBackend("bundled", 1, f"{reason}, but the mkl package is not installed", cpu)
    # The layer is set through MKL's API, not the environment, which child processes inherit.
    layer = os.environ.get("MKL_THREADING_LAYER", "").upper()
    openmp = _torch_openmp() if layer in ("", "GNU") else None
    if openmp is not None:
        ctypes.CDLL(str(openmp), mode=ctypes.RTLD_GLOBAL)  # libgomp.so.1, found by MKL's GNU layer
    try:
        mkl = ctypes.CDLL(str(runtime), mode=ctypes.RTLD_GLOBAL)
    except OSError as error:
        return BlasBackend("bundled", 1, f"{reason}, but loading {runtime.name} failed: {error}", cpu)
    if not layer:
        layer = "GNU" if openmp is not None else "INTEL"  # INTEL: the mkl wheel's own libiomp5
        mkl.MKL_Set_Threading_Layer(ctypes.c_int(_MKL_THREADING_LAYERS[layer]))
    if "MKL_NUM_THREADS" not in os.environ:
        mkl.MKL_Set_Num_Threads(ctypes.c_int(1))
    threads = int(mkl.MKL_Get_Max_Threads())
    _limit_openblas_pools()
    return BlasBackend("mkl", threads, f"{reason}; {runtime}, {layer} threading", cpu)


def configure() -> BlasBackend:
    """Bind CHOLMOD's BLAS for this CPU (or as MESHFG_BLAS says); the entry points call it before
    cvxopt is loaded. Idempotent; returns the backend in use. Raises BlasSettingError for an
    unknown MESHFG_BLAS."""
    global _backend
    if _backend is not None:
        return _backend
    cpu, vendor, setting = cpu_model(), cpu_vendor(), os.environ.get("MESHFG_BLAS")
    name = choose(vendor, setting)
    reason = f"MESHFG_BLAS={setting}" if setting else f"chosen for {vendor or 'an unknown CPU vendor'}"
    if name == "bundled":
        _limit_openblas_pools()
        _backend = BlasBackend("bundled", 1, f"{reason}: cvxopt's own OpenBLAS", cpu)
    elif "cvxopt.cholmod" in sys.modules:
        _backend = BlasBackend("bundled", 1, f"{reason}, but cvxopt was imported before MKL could be bound", cpu)
    else:
        _backend = _bind_mkl(cpu, reason)
    return _backend
