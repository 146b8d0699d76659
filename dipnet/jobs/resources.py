"""Size checks before allocation: estimate a run's memory from its config, refuse what cannot fit.

:func:`estimate_memory` adds up the largest arrays a reconstruction job allocates, from the
config alone (``V = N^d`` voxels, ``K`` dips, ``M`` slabs; bytes):

* grid and outputs: voxel centres ``8 d V``, occupancy / binary / working mask ``~24 V``;
* the truth occupancy of simulated sources: centres, shifted sub-samples and masks,
  ``8 (3 d + 2) V`` (sub-samples are taken one offset at a time);
* operator: ``splat`` caches ``24 K V_ball`` bytes of weights up to 512 MiB, else works in
  chunks of ``2^22`` pairs (``~24 2^22``); ``fourier`` holds ``~128 V`` of NUFFT work arrays
  (an upsampled complex grid); ``rotate_sum`` a rotated volume per orientation (``~32 V``);
* solver: ``minnorm`` with Cholesky (``K M <= max_cholesky_rows``) the sparse ``B`` with
  ``nnz = 2 K V_ball`` (built as COO with int64 indices, concatenated, then CSR and its
  transpose: ``~72`` bytes per non-zero) and the dense ``B B^T`` (``8 (K M)^2``); the
  iterative solvers (``lsmr``, ``lsqr``, minnorm's fallback) ``~6`` vectors of ``V`` and of
  ``K M``; ``voxel`` ``~200 V + 250 MB`` (parameters, gradient, Adam moments, coarse-to-fine
  copies and the autograd graph through the operator; the constant covers the NUFFT plans and
  work arrays that do not grow with ``V``); ``implicit`` the MLP activations forward and
  backward (``12 V w (L + 1)``, width ``w``, ``L`` hidden layers) and its grid encoding
  (``~4 f V`` per level);
* the measurement ``~32 K M``.

These are the dominant terms, enough to refuse a run that needs 24 PB before anything is
allocated. Measured (peak RSS minus the RSS after imports, one run each, 1 thread) against
the estimate: default config (40^3, K = 120, minnorm Cholesky) 746 MB vs ~800 MB; voxel 64^3
(fourier) 286 MB vs ~300 MB, voxel 240^3 with K = 5,760 (fourier, single precision) peak RSS
2.03 GB with imports and the operator vs 3.0 GB (solver part, ``800 V`` before: 11 GB); lsmr 96^3, K = 60 208 MB vs
~290 MB; implicit 48^3 157 MB vs ~280 MB. :func:`check_memory` raises :class:`ResourceError` when the estimate exceeds
the available memory (``psutil`` if installed, else ``MemAvailable`` of ``/proc/meminfo``, else
``os.sysconf``).
"""

from __future__ import annotations

import math

from omegaconf import DictConfig, OmegaConf

from dipnet.core.memory import MemoryEstimate, ResourceError, available_memory, format_bytes
from dipnet.jobs.options import instantiates
from dipnet.preprocessing.sources import RecordedSource

SPLAT_CACHE_BYTES = 1 << 29
CHUNK_PAIRS = 1 << 22


def estimate_memory(cfg: DictConfig) -> MemoryEstimate:
    """The memory a reconstruction job with config ``cfg`` needs (see the module docstring)."""
    def get(key: str, default=None):
        value = OmegaConf.select(cfg, key, default=default, throw_on_missing=False)
        return default if value is None else value

    d, n, k = int(get("ndim", 3)), int(get("resolution")), int(get("n_dips", 1))
    m = int(get("n_slabs") or n)
    voxels = float(n) ** d
    ball = voxels * (math.pi / 6 if d == 3 else math.pi / 4)  # working ball's share of the grid
    solver = str(get("solver._target_", "")).rsplit(".", 1)[-1].lower()
    backend = str(get("operator.backend", "auto"))
    if backend == "auto":  # as dipnet.operators.select_backend
        backend = "splat" if k * voxels <= 2_000_000 else "fourier"
    parts = {"grid": (8 * d + 24) * voxels, "measurement": 32.0 * k * m}
    if not instantiates(cfg, "source", RecordedSource):
        parts["truth"] = 8 * (3 * d + 2) * voxels
    pairs = k * ball
    if backend == "splat":
        parts["operator"] = 24 * pairs if 24 * pairs <= SPLAT_CACHE_BYTES else 24.0 * CHUNK_PAIRS + 8 * d * ball
    elif backend == "fourier":
        parts["operator"] = 128 * voxels
    else:
        parts["operator"] = 32 * voxels
    rows = k * m
    if "minnorm" in solver and (get("solver.method", "auto") == "cholesky" or (
            get("solver.method", "auto") == "auto" and rows <= int(get("solver.max_cholesky_rows", 6000)))):
        parts["solver"] = 72 * 2 * pairs + 8.0 * rows**2
    elif "voxel" in solver:
        parts["solver"] = 200 * voxels + 250e6
    elif "implicit" in solver:
        width, layers = int(get("solver.hidden_width", 64)), int(get("solver.hidden_layers", 2))
        levels, features = int(get("solver.encoding.levels", 6)), int(get("solver.encoding.features", 2))
        parts["solver"] = 12 * voxels * width * (layers + 1) + 4 * features * levels * voxels
    else:
        parts["solver"] = 8 * 6 * (voxels + rows)
    return MemoryEstimate(parts)


def check_memory(cfg: DictConfig, available: int | None = None) -> MemoryEstimate:
    """Raise :class:`ResourceError` when the run needs more than ``available`` bytes (default:
    :func:`available_memory`); returns the estimate."""
    estimate = estimate_memory(cfg)
    available = available_memory() if available is None else available
    if available is not None and estimate.total > available:
        raise ResourceError(f"resolution={cfg.resolution} (ndim={cfg.get('ndim')}, n_dips={cfg.get('n_dips')}) "
                            f"needs {estimate.describe()}, this machine has {format_bytes(available)} available")
    return estimate

