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
CPUs and cvxopt's bundled OpenBLAS on every other CPU (vendor_id in /proc/cpuinfo), because:

- Intel (the 2-core Xeon VM the project was first tuned on), organ-scale state block (31,944
  dofs, METIS ordering): numeric factorisation 0.50 s (bundled) against 0.36 s (MKL, 1 thread)
  and 0.26 s (MKL, 2 threads); one solve 20.8 ms against 17.2 and 11.7 ms. Organ-scale window
  update median 1.25 s against 0.88-0.92 s, paper-scale 25.9 ms against 23.2-24.9 ms. On a
  later 2-core Xeon VM (AVX-512, KVM), `meshfg bench` with MESHFG_BLAS=mkl and =bundled back to
  back: organ-scale update p95 0.83 s against 1.06 s (linear solves 34 against 51 ms per
  update), paper scale 20.6 against 20.8 ms, one small-window update 17.3 against 18.0 ms.
- AMD (2-core EPYC, Zen 4 with AVX-512, KVM), the same blocks (paper scale: 1,536 dofs, AMD
  ordering); medians of repeated factorisations and solves, each configuration in a fresh
  interpreter, best of five interleaved rounds (other processes shared the machine; see below):

  | BLAS                                  | paper factor | paper solve | organ factor | organ solve |
  |---------------------------------------|--------------|-------------|--------------|-------------|
  | cvxopt's OpenBLAS 0.3.15 (1 thread)   | 2.03 ms      | 0.114 ms    | 462 ms       | 18.9 ms     |
  | MKL 2026.2, 2 threads (GNU OpenMP)    | 3.66 ms      | 0.109 ms    | 393 ms       | 17.0 ms     |
  | MKL 2026.2, 1 thread                  | 3.10 ms      | 0.110 ms    | 634 ms       | 17.3 ms     |

  MKL_VERBOSE names no AVX2 or AVX-512 code path on this CPU ("Intel(R) Architecture
  processors"): MKL's 1-thread factorisations are 1.4-1.5x slower than OpenBLAS's Zen kernels,
  and its two threads win back 15% at organ scale but cost 80% at paper scale, where a window
  update makes one new factorisation. Solves differ by less than 10%. With other processes on
  the cores, MKL's two threads fell far behind: in three of the five rounds its paper-scale
  factorisation took 27-66 ms and once the organ-scale one 4.9 s, while the single-threaded
  OpenBLAS stayed within 2.03-2.09 ms and 462-494 ms in every round; in `meshfg bench` under
  such load the organ-scale p95 was 12.7 and 25.4 s with MKL against 1.7 and 2.1 s with OpenBLAS
  (paper scale 36-42 ms against 38-55 ms). With the machine to itself, two `meshfg bench` runs
  back to back: paper-scale p95 27.1 ms with OpenBLAS against 32.4 ms with MKL, organ-scale p95
  1.07 s against 1.16 s, one small-window update 19.2 against 21.0 ms. On AMD the
  single-threaded OpenBLAS is therefore chosen, and MKL is not loaded. Threaded OpenBLAS builds
  that export the plain symbols (Debian's libopenblas0-pthread 0.3.21, the ngsolve-openblas
  wheel 0.3.33) factor the organ-scale block in 323-327 ms (paper scale 2.24-2.27 ms), but need
  the system's libgfortran.so.5 (no wheel ships it under that name) and collapsed like MKL under
  load (1.1-3.0 s); BLIS (Debian's libblis4-pthread 0.9) took 2.5 s.

With MKL, it runs on the GNU OpenMP runtime that torch ships (loaded here by path, without
importing torch), so a process that also uses torch has one OpenMP runtime, not two.
MKL_NUM_THREADS and MKL_THREADING_LAYER are honoured when set. With either backend the
process's OpenBLAS pools (numpy's, scipy's) are held to one thread: their threads, woken by
PCG's long dot products and the estimator's vector work, spin after each call; they took the
cores from MKL's (the organ-scale preconditioner application 139 ms against 70 ms on the Intel
machine), and with another process on the second core a 40k-element norm took 10 ms instead of
microseconds (the live pipeline runs two node processes on two cores).
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
    """The CPU model name and the number of cores this process may run on."""
    name = _cpuinfo_field("model name") or platform.processor() or platform.machine() or "unknown CPU"
    return f"{name}, {len(os.sched_getaffinity(0))} cores"


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
        mkl.MKL_Set_Num_Threads(ctypes.c_int(len(os.sched_getaffinity(0))))
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
