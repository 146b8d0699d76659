"""The paper's linear baseline: the minimum-norm solution of ``B f = g``, then Otsu.

``B`` is the dip operator (slab volumes in mm^3 from occupancy fractions, so ``f`` is an
occupancy and needs no rescaling), ``g`` the measured profiles flattened to ``K*M``.
Every method solves the same Tikhonov problem

    min_f ||B f - g||^2 + s ||f||^2,   s = tikhonov * mean(diag(B B^T)),

whose solution ``f = B^T (B B^T + s I)^{-1} g`` tends to the minimum-norm solution
``B^+ g`` as ``s -> 0``. ``tikhonov`` is relative to the mean squared row norm of ``B``, so
it does not depend on units or grid size. ``tikhonov=0`` is the paper's plain minimum-norm
solution. A small weight keeps noise and model mismatch from exploding: with noise of
0.05% of the largest slab volume plain min-norm falls to IoU 0.26 (``1e-3``: 0.997), and on
the exact slab areas of a disk (64^2, 20 angles: voxelisation is the only error) to IoU
0.22 (``1e-3``: 0.987). The default ``0.1`` was chosen on dips simulated from the exact
geometry (noise-free, unquantised), IoU after Otsu; it costs little there and buys
robustness to noise:

=========================  ======  ======  ======  ======
tikhonov                   1e-3    1e-2    0.1     0.3
=========================  ======  ======  ======  ======
ball 32^3, 100 dips        0.994   0.995   0.996   0.993
torus 32^3, 100 dips       0.974   0.973   0.970   0.971
chamber box 32^3, 100      0.972   0.972   0.967   0.962
bunny 32^3, 100 dips       0.914   0.913   0.913   0.900
elephant 128^2, 20 dips    0.967   0.966   0.967   0.964
chamber box 128^2, 20      0.992   0.992   0.993   0.995
=========================  ======  ======  ======  ======

Methods
-------
* ``cholesky``: the explicit sparse ``B`` (the splat backend's matrix, exactly the splat and
  rotate_sum operators; see :func:`matrix_backend` for fourier), dense ``B B^T + s I`` and a Cholesky factorisation.
  ``B B^T`` is singular in practice - every profile sums to the object volume, so the rows of
  different orientations are linearly dependent, and slabs outside the working ball are
  empty rows - so the shift also makes the factorisation possible. With ``tikhonov=0``, or
  if the factorisation still fails, the rank-revealing fallback is an eigendecomposition of
  ``B B^T`` that drops eigenvalues below ``rcond * max``: the exact pseudo-inverse.
  Memory: ``8 (K M)^2`` bytes.
* ``lsqr`` / ``lsmr``: scipy's iterative solvers on the matrix-free operator (any backend),
  started at zero, so they converge to the minimum-norm (damped) solution; the damping is
  ``sqrt(s)`` with ``mean(diag(B B^T))`` estimated by seeded Hutchinson probes (within
  about 10%: the damping is a regularisation weight, not a precise constant).
* ``auto``: ``cholesky`` when ``K*M <= max_cholesky_rows``, its memory (:func:`cholesky_bytes`:
  the dense Gram matrix plus the sparse ``B``) is at most ``max_cholesky_bytes`` and the
  operator has an explicit matrix (:func:`matrix_backend`), else ``lsmr`` on the operator itself
  (matrix-free: memory ``O(N^d + K M)`` besides the operator).

Which operator and method a run used, and why, is in ``info["operator"]``, ``info["method"]``
and ``info["operator_reason"]`` (logged, and written to ``metrics.json`` by the pipeline).

The result keeps the raw least-squares values (they leave ``[0, 1]``); the threshold is
Otsu's over the working-region voxels (or a given number).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
import torch
from skimage.filters import threshold_otsu
from tqdm.auto import tqdm

from dipnet.core.counts import is_real, whole_number
from dipnet.core.flags import checked_flag
from dipnet.core.measurement import DipMeasurement
from dipnet.core.keywords import forwards_to
from dipnet.operators import SPLAT_MATRIX_BACKENDS, DipOperator, backend_name, make_operator
from dipnet.core.reconstruction import Reconstruction
from dipnet.solvers.base import Solver, checked_threshold, measured_profiles
from dipnet.solvers.progress import stop_bar

log = logging.getLogger(__name__)

METHODS = ("auto", "cholesky", "lsqr", "lsmr")
_HUTCHINSON_PROBES = 16


class OperatorChoiceError(ValueError):
    """The chosen operator cannot serve the chosen method."""


def matrix_backend(operator: DipOperator) -> str:
    """The backend whose explicit matrix the Cholesky method factorises for ``operator``.

    ``splat`` and ``rotate_sum`` (alias ``grid_sample``) are the same linear map, so their
    matrix is the operator itself. A ``fourier`` operator has no explicit matrix; when
    ``operator=auto`` chose it, the splat matrix stands in (the two discretisations differ by
    0.2-0.6%, see docs/guide/operators.md) and the solver's ``info`` says so; when the user chose
    it, :class:`OperatorChoiceError` (building its ``B B^T`` would take one forward and adjoint
    per row: about 800 s for 120 dips at 40^3).
    """
    name = backend_name(operator)
    if name in SPLAT_MATRIX_BACKENDS:
        return name
    if getattr(operator, "auto_selected", False):
        return "splat"
    raise OperatorChoiceError(f"minnorm method=cholesky needs an explicit matrix, which operator={name} does not "
                              f"have: use solver.method=lsmr (matrix-free on {name}) or operator=splat")


def operator_matrix(operator: DipOperator) -> scipy.sparse.csr_matrix:
    """The explicit ``(K*M, N^d)`` CSR matrix (float64) for ``operator`` (see :func:`matrix_backend`)."""
    matrix_backend(operator)
    if hasattr(operator, "to_sparse"):
        return operator.to_sparse()
    return make_operator(operator.grid, operator.directions, operator.n_slabs, backend="splat").to_sparse()


def cholesky_bytes(operator: DipOperator) -> int:
    """Memory (bytes) of the ``cholesky`` method: the dense ``(K M)^2`` Gram matrix (float64) and
    the explicit sparse ``B`` (about two slabs per voxel and orientation, 12 bytes per entry)."""
    rows = operator.n_orientations * operator.n_slabs
    return 8 * rows**2 + 12 * 2 * operator.n_orientations * math.prod(operator.grid.shape)


def otsu_threshold(values: np.ndarray) -> float:
    """Otsu's threshold of ``values`` (any shape); a constant array gives its value."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0 or np.ptp(values) == 0:
        return float(values[0]) if values.size else 0.0
    return float(threshold_otsu(values))


class MinNormSolver(Solver):
    """Minimum-norm (optionally Tikhonov-damped) least squares, then a threshold.

    Args:
        method: ``"auto"``, ``"cholesky"``, ``"lsqr"`` or ``"lsmr"`` (see the module docstring).
        tikhonov: relative Tikhonov weight ``s / mean(diag(B B^T))``, finite and >= 0.
        iter_lim: iteration limit of ``lsqr`` / ``lsmr``, a whole number >= 1.
        atol, btol: stopping tolerances of ``lsqr`` / ``lsmr`` (scipy's meaning), finite and >= 0.
        max_cholesky_rows: largest ``K*M`` for which ``auto`` picks ``cholesky``.
        max_cholesky_bytes: largest :func:`cholesky_bytes` for which ``auto`` picks ``cholesky``, bytes (finite).
        rcond: relative eigenvalue cut-off of the pseudo-inverse fallback, finite and >= 0.
        threshold: ``"otsu"`` or a fixed occupancy level in ``(0, 1)``.
        progress: show a progress bar.
    """

    name = "minnorm"

    def __init__(self, method: str = "auto", tikhonov: float = 0.1, iter_lim: int = 300,
                 atol: float = 1e-6, btol: float = 1e-6, max_cholesky_rows: int = 6000,
                 max_cholesky_bytes: float = 2e9, rcond: float = 1e-10, threshold: str | float = "otsu",
                 progress: bool = True) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown minnorm method {method!r}; choose one of {METHODS}")
        if not is_real(tikhonov) or not 0 <= tikhonov < math.inf:  # inf damps every voxel to 0: an empty result
            raise ValueError(f"tikhonov must be a finite number >= 0 (relative Tikhonov weight), got {tikhonov!r}")
        iter_lim = whole_number("iter_lim", iter_lim, low=1)
        max_cholesky_rows = whole_number("max_cholesky_rows", max_cholesky_rows, low=1)
        self.method, self.tikhonov, self.iter_lim = method, float(tikhonov), iter_lim
        for name, value, low in (("atol", atol, 0.0), ("btol", btol, 0.0), ("rcond", rcond, 0.0),
                                 ("max_cholesky_bytes", max_cholesky_bytes, 1.0)):  # NaN compares false: no limit
            if not is_real(value) or not low <= value < math.inf:
                raise ValueError(f"{name} must be a finite number >= {low:g}, got {value!r}")
        for name, value in (("atol", atol), ("btol", btol)):  # relative: 1 or more stops at the first step, x ~ 0
            if value >= 1:
                raise ValueError(f"{name} must be below 1 (a relative stopping tolerance of lsqr / lsmr: 1 or more "
                                 f"is met by the first iterate, which explains little of the dips), got {value!r}")
        self.atol, self.btol, self.rcond = float(atol), float(btol), float(rcond)
        self.threshold = checked_threshold(threshold, "otsu")
        self.max_cholesky_rows, self.progress = max_cholesky_rows, checked_flag("progress", progress)
        self.max_cholesky_bytes = float(max_cholesky_bytes)

    # ------------------------------------------------------------------ public
    def solve(self, measurement: DipMeasurement, operator: DipOperator) -> Reconstruction:
        """Reconstruct on ``operator.grid``; ``info`` holds method, seconds, iterations, residual."""
        g = measured_profiles(measurement, operator).reshape(-1).numpy()
        start = time.perf_counter()
        method, why = self._method_for(operator, g.size)
        if method == "cholesky":
            used = matrix_backend(operator)
            f, info = self._solve_cholesky(operator, g)
        else:
            used = backend_name(operator)
            f, info = self._solve_iterative(operator, g, method)
        chosen = backend_name(operator)
        if used != chosen:
            why += f"; the {chosen} operator (chosen by operator=auto) has no explicit matrix, so its {used} equivalent"
        log.info("minnorm: method %s on the %s operator (%s)", method, used, why)
        seconds = time.perf_counter() - start
        vol = torch.from_numpy(f.reshape(operator.grid.shape))
        with torch.no_grad():
            fitted = operator(vol).reshape(-1).numpy()
        residual = float(np.linalg.norm(fitted - g) / max(np.linalg.norm(g), 1e-300))
        mask = operator.mask.cpu().numpy()
        level = otsu_threshold(f.reshape(operator.grid.shape)[mask]) if self.threshold == "otsu" \
            else float(self.threshold)
        info = {"solver": self.name, "method": method, "operator": used, "operator_reason": why,
                "tikhonov": self.tikhonov, "seconds": seconds, "relative_residual": residual, **info}
        return Reconstruction(occupancy=vol.to(torch.float32), grid=operator.grid, threshold=level, info=info)

    def _method_for(self, operator: DipOperator, rows: int) -> tuple[str, str]:
        """The method for ``rows = K*M`` equations on ``operator`` and why it was taken."""
        if self.method != "auto":
            return self.method, f"method={self.method}"
        if rows > self.max_cholesky_rows:
            return "lsmr", f"method=auto: K*M = {rows} > max_cholesky_rows = {self.max_cholesky_rows}"
        try:
            matrix_backend(operator)
        except OperatorChoiceError:
            return "lsmr", f"method=auto: operator={backend_name(operator)} has no explicit matrix for Cholesky"
        need = cholesky_bytes(operator)
        if need > self.max_cholesky_bytes:
            return "lsmr", f"method=auto: Cholesky would need {need / 1e9:.1f} GB > max_cholesky_bytes"
        return "cholesky", f"method=auto: K*M = {rows} <= max_cholesky_rows = {self.max_cholesky_rows}"

    # ------------------------------------------------------------------ methods
    def _solve_cholesky(self, operator: DipOperator, g: np.ndarray) -> tuple[np.ndarray, dict]:
        with tqdm(total=3, desc="minnorm cholesky", disable=not self.progress, leave=False) as bar:
            mat = operator_matrix(operator)
            bar.update()
            gram = _dense_gram(mat)
            bar.update()
            diag = np.diag_indices_from(gram)
            shift = self.tikhonov * float(gram[diag].mean())
            y, factorisation = None, "eigh-pinv"
            if shift > 0:
                gram[diag] += shift
                try:
                    factor = scipy.linalg.cho_factor(gram, lower=True, overwrite_a=True, check_finite=False)
                    y, factorisation = scipy.linalg.cho_solve(factor, g, check_finite=False), "cholesky"
                except np.linalg.LinAlgError:
                    gram = _dense_gram(mat)  # the failed factorisation overwrote it
            if y is None:
                w, u = scipy.linalg.eigh(gram, overwrite_a=True, check_finite=False)
                keep = w > self.rcond * max(w.max(), 1e-300)
                y = u[:, keep] @ ((u[:, keep].T @ g) / (w[keep] + shift))
            bar.update()
        return mat.T @ y, {"iterations": 0, "shift": shift, "factorisation": factorisation}

    def _solve_iterative(self, operator: DipOperator, g: np.ndarray, method: str) -> tuple[np.ndarray, dict]:
        base = operator.as_linear_operator()
        damp = float(np.sqrt(self.tikhonov * _mean_gram_diagonal(operator))) if self.tikhonov > 0 else 0.0
        with tqdm(total=self.iter_lim, desc=f"minnorm {method}", disable=not self.progress, leave=False) as bar:
            def rmatvec(y: np.ndarray) -> np.ndarray:
                bar.update()  # one adjoint per iteration
                return base.rmatvec(y)

            op = scipy.sparse.linalg.LinearOperator(base.shape, matvec=base.matvec, rmatvec=rmatvec,
                                                    dtype=np.float64)
            tol = {"damp": damp, "atol": self.atol, "btol": self.btol}
            out = (scipy.sparse.linalg.lsqr(op, g, iter_lim=self.iter_lim, **tol) if method == "lsqr"
                   else scipy.sparse.linalg.lsmr(op, g, maxiter=self.iter_lim, **tol))
            stop_bar(bar, "converged")
        return out[0], {"iterations": int(out[2]), "stop_reason": int(out[1]), "damp": damp}


def _dense_gram(mat: scipy.sparse.csr_matrix, block_rows: int = 512) -> np.ndarray:
    """Dense ``B B^T`` ``(R, R)`` float64, built in row blocks so that the (nearly dense)
    sparse product never exists whole: peak memory stays close to ``8 R^2`` bytes."""
    rows = mat.shape[0]
    out = np.empty((rows, rows))
    right = mat.T.tocsc()
    for r0 in range(0, rows, block_rows):
        out[r0:r0 + block_rows] = (mat[r0:r0 + block_rows] @ right).toarray()
    return out


def _mean_gram_diagonal(operator: DipOperator, seed: int = 0) -> float:
    """``mean(diag(B B^T)) = ||B||_F^2 / (K M)`` by Hutchinson's estimator: the mean of
    ``||B z||^2`` over seeded Rademacher probes ``z`` (one at a time, to bound memory)."""
    gen = torch.Generator().manual_seed(seed)
    total = 0.0
    with torch.no_grad():
        for _ in range(_HUTCHINSON_PROBES):
            z = torch.randint(0, 2, operator.grid.shape, generator=gen).to(torch.float64) * 2 - 1
            total += float(operator(z).pow(2).sum())
    return total / _HUTCHINSON_PROBES / (operator.n_orientations * operator.n_slabs)


class LSQRSolver(MinNormSolver):
    """:class:`MinNormSolver` with ``method="lsqr"``."""

    name = "lsqr"

    @forwards_to(MinNormSolver)
    def __init__(self, **options) -> None:
        super().__init__(method="lsqr", **options)


class LSMRSolver(MinNormSolver):
    """:class:`MinNormSolver` with ``method="lsmr"``."""

    name = "lsmr"

    @forwards_to(MinNormSolver)
    def __init__(self, **options) -> None:
        super().__init__(method="lsmr", **options)
