"""Per-voxel uncertainty of a reconstruction: a linearised Gaussian posterior, sampled.

Model
-----
Around the current reconstruction the occupancy is ``f = f_hat + d`` with a Gaussian prior
deviation ``d ~ N(0, P)``, ``P = tau^2 diag(w)``, and the slab volumes are linear in ``f``
(``g = B f + e``, ``e ~ N(0, sigma^2 I)``, ``B`` the dip operator). The posterior of ``d`` given
the dips is Gaussian with covariance ``Sigma = (P^-1 + B^T B / sigma^2)^-1``, which does not depend
on the measured values; exact samples of it come from Matheron's rule (conditioning by
perturbation):

    d_s = eta_s - P B^T (B P B^T + sigma^2 I)^-1 (B eta_s + e_s),   eta_s ~ N(0, P), e_s ~ N(0, sigma^2 I)

with one dense Cholesky factorisation of the ``(K M, K M)`` matrix ``B P B^T + sigma^2 I`` and
two sparse products per batch of samples: no iterative solve per sample.

* ``w``: where the occupancy may still be wrong. A binary object is known except near its
  boundary, so ``w = floor + (1 - floor) 4 q (1 - q)`` with ``q`` the reconstruction's binary
  volume blurred by ``band_voxels``; ``tau = 0.5`` (a boundary voxel may flip between 0 and 1).
  This makes the posterior object-dependent: the uncertainty sits on the parts of the boundary the
  dips do not pin down (e.g. the sides of an object seen only from near the spin axis).
* ``sigma^2``: the mean squared misfit of the binary reconstruction to the measured slabs (noise
  and model error together) or the measurement's own ``sigma`` if larger, rescaled to the coarse slabs.
* Grid: the posterior lives on a coarse grid (``resolution`` voxels per axis, default 32) and
  ``K M`` stays below ``max_rows`` (with many dips the slabs get thicker and the grid coarser, to
  bound the Cholesky and Gram costs); maps are interpolated back onto the reconstruction grid.

Outputs per voxel: the posterior standard deviation ``std`` (occupancy units) and
``p_wrong = Phi(-|f_hat - threshold| / std)``, the probability that the voxel's binary call is
wrong. Summaries (:func:`summarise`): mean ``std`` over the support (the reconstructed object
dilated by two voxels), the fraction of support voxels with ``p_wrong > 0.2`` and the expected
misclassified volume over the reconstructed volume. :func:`calibration_by_decile` measures how
well ``p_wrong`` ranks the voxels that are actually wrong; :func:`sure_error_rate` whether the voxels it calls sure
are right (the prior's doubt sits on the reconstructed boundary: a part the reconstruction misses far from it, e.g.
along a missing cone, gets the ``floor`` and a ``p_wrong`` of about 1e-5).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.ndimage
import scipy.special
import torch
import torch.nn.functional as F

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.operators import DipOperator, make_operator
from dipnet.core.reconstruction import Reconstruction
from dipnet.solvers.base import measured_profiles, measured_sigma
from dipnet.solvers.minnorm import _dense_gram, operator_matrix

log = logging.getLogger(__name__)

PRIOR_STD = 0.5  # tau: a boundary voxel may flip between 0 and 1
UNCERTAIN_P_WRONG = 0.2  # a voxel is "uncertain" when its binary call is wrong with at least this probability
SURE_P_WRONG = 0.05  # a voxel the map calls "sure": its binary call wrong with less than this probability


@dataclass
class Posterior:
    """Samples of the linearised posterior deviation on a coarse grid.

    Attributes:
        grid: the coarse grid of the samples.
        samples: posterior deviations ``d_s``, ``(S, N_c^d)`` float64 (flattened coarse volumes).
        noise_var: slab noise variance on the coarse slabs, mm^6.
        n_slabs: slabs per profile on the coarse grid.
    """

    grid: Grid
    samples: np.ndarray
    noise_var: float
    n_slabs: int

    def std(self) -> np.ndarray:
        """Posterior standard deviation per coarse voxel, ``grid.shape`` (occupancy units)."""
        return self.samples.std(axis=0, ddof=1).reshape(self.grid.shape)

    def profile_samples(self, directions: torch.Tensor) -> np.ndarray:
        """The samples seen through dips along ``directions`` ``(C, d)``: ``(S, C, M_c)`` mm^3."""
        mat = operator_matrix(make_operator(self.grid, directions, self.n_slabs, backend="splat"))
        return (mat @ self.samples.T).T.reshape(len(self.samples), len(directions), self.n_slabs)


def check_posterior_options(resolution: int, n_samples: int, band_voxels: float, floor: float) -> None:
    """Raise ``ValueError`` for options of :func:`fit_posterior` it cannot use: ``n_samples < 2``, ``floor``
    outside ``(0, 1]``, ``resolution < 4`` (voxels per axis), or ``band_voxels`` (the boundary band's blur, in
    posterior-grid voxels; 0: no blur) negative or not finite (a negative blur was taken as 0)."""
    if n_samples < 2 or not 0 < floor <= 1 or resolution < 4:
        raise ValueError(f"need n_samples >= 2, 0 < floor <= 1 and resolution >= 4, got {n_samples}, {floor}, "
                         f"{resolution}")
    if not 0 <= band_voxels < math.inf:  # NaN fails too
        raise ValueError(f"band_voxels must be >= 0 (the width of the uncertain boundary band, in posterior-grid "
                         f"voxels; 0: no band), got {band_voxels!r}")


def fit_posterior(reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator | None = None,
                  *, resolution: int = 32, n_samples: int = 64, band_voxels: float = 1.5, floor: float = 0.05,
                  seed: int = 0, max_rows: int = 4000, max_work: float = 6e7) -> Posterior:
    """Sample the linearised posterior around ``reconstruction`` given ``measurement`` (module docstring).

    Args:
        reconstruction: the current estimate (its binary volume places the uncertain band).
        measurement: the dips so far (directions ``(K, d)``, profiles ``(K, M)`` mm^3).
        operator: the reconstruction's operator (built if ``None``), for the misfit.
        resolution: voxels per axis of the coarse posterior grid (at most the reconstruction's).
        n_samples: posterior samples ``S`` (the std has a relative error of about ``1 / sqrt(2 S)``).
        band_voxels: blur (Gaussian sigma, coarse voxels) of the binary volume that sets ``w``.
        floor: prior weight ``w`` far from the boundary, in ``(0, 1]``.
        seed: random seed of the samples.
        max_rows: bound on ``K M_c`` (the Cholesky costs ``(K M_c)^3 / 3``): with many dips the
            posterior's slabs are made thicker than its voxels, ``M_c = max_rows // K`` (at least 4).
        max_work: bound on ``K^2 N_c^d`` (the cost of the Gram matrix ``B P B^T``): with many dips
            the posterior grid is made coarser than ``resolution`` (at least 8 voxels per axis);
            the default keeps the 32^3 grid up to 43 dips.
    """
    grid = reconstruction.grid
    check_posterior_options(resolution, n_samples, band_voxels, floor)
    if operator is None:
        operator = make_operator(grid, measurement.directions, grid.n)
    affordable = int((max_work / measurement.n_orientations**2) ** (1.0 / grid.ndim))
    coarse = Grid(min(grid.n, max(8, min(int(resolution), affordable))), grid.ndim, grid.extent)
    n_slabs = max(4, min(coarse.n, int(max_rows) // measurement.n_orientations))
    noise_var = misfit_variance(reconstruction, measurement, operator) * operator.n_slabs / n_slabs
    weights = boundary_weights(reconstruction.binary, coarse, band_voxels, floor)
    prior_var = PRIOR_STD**2 * weights.reshape(-1)
    mat = operator_matrix(make_operator(coarse, measurement.directions, n_slabs, backend="splat"))
    gram = _dense_gram(mat @ scipy.sparse.diags(np.sqrt(prior_var)))
    noise_var = max(noise_var, 1e-6 * float(np.diag(gram).mean()))
    gram[np.diag_indices_from(gram)] += noise_var
    factor = scipy.linalg.cho_factor(gram, lower=True, overwrite_a=True, check_finite=False)
    rng = np.random.default_rng(seed)
    eta = rng.standard_normal((n_samples, prior_var.size)) * np.sqrt(prior_var)
    noise = rng.standard_normal((n_samples, mat.shape[0])) * math.sqrt(noise_var)
    rhs = (mat @ eta.T) + noise.T  # (R, S)
    correction = (mat.T @ scipy.linalg.cho_solve(factor, rhs, check_finite=False)).T * prior_var
    return Posterior(coarse, eta - correction, noise_var, n_slabs)


def misfit_variance(reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator) -> float:
    """Slab noise variance (mm^6) on the operator's slabs: the mean squared misfit of the binary
    reconstruction, or the measurement's mean ``sigma^2`` on those slabs (:func:`~dipnet.solvers.base.measured_sigma`)
    if larger; never below a tiny floor."""
    with torch.no_grad():
        predicted = operator(reconstruction.occupancy.detach().double().clamp(0.0, 1.0))
    misfit = float((predicted - measured_profiles(measurement, operator)).pow(2).mean())
    sigma = measured_sigma(measurement, operator)
    stated = float(sigma.pow(2).mean()) if sigma is not None else 0.0
    return max(misfit, stated, (1e-6 * operator.grid.voxel_volume) ** 2)


def boundary_weights(binary: np.ndarray, coarse: Grid, band_voxels: float, floor: float) -> np.ndarray:
    """Prior weight ``w`` on ``coarse``: ``floor`` away from the object's boundary, 1 on it; ``coarse.shape``."""
    fraction = resample(torch.as_tensor(binary, dtype=torch.float64), coarse.shape, mode="area")
    q = scipy.ndimage.gaussian_filter(fraction, sigma=band_voxels, mode="constant")
    w = floor + (1.0 - floor) * 4.0 * q * (1.0 - q)
    return np.where(coarse.working_mask().numpy(), w, floor)


def voxel_maps(reconstruction: Reconstruction, posterior: Posterior) -> dict[str, np.ndarray]:
    """``std`` and ``p_wrong`` on the reconstruction's grid (float32 volumes, ``grid.shape``)."""
    grid = reconstruction.grid
    std = resample(torch.from_numpy(posterior.std()), grid.shape, mode="trilinear" if grid.ndim == 3 else "bilinear")
    std = np.maximum(std, 1e-9)
    margin = np.abs(reconstruction.occupancy.detach().double().numpy() - reconstruction.threshold)
    p_wrong = scipy.special.ndtr(-margin / std)
    p_wrong = np.where(grid.working_mask().numpy(), p_wrong, 0.0)
    return {"std": std.astype(np.float32), "p_wrong": p_wrong.astype(np.float32)}


def support(binary: np.ndarray, dilation: int = 2) -> np.ndarray:
    """The voxels the summaries look at: the reconstructed object dilated by ``dilation`` voxels."""
    return scipy.ndimage.binary_dilation(np.asarray(binary, bool), iterations=dilation)


def summarise(maps: dict[str, np.ndarray], binary: np.ndarray) -> dict[str, float]:
    """Metrics: ``uncertainty_mean`` (mean std over the support), ``uncertain_fraction`` (support
    voxels with ``p_wrong > 0.2``) and ``expected_error_fraction`` (sum of ``p_wrong``, the expected
    wrong voxels, over the reconstructed volume in voxels: a share of the object's volume, above 1
    when more voxels are expected wrong than were reconstructed)."""
    where = support(binary)
    if not where.any():
        return {"uncertainty_mean": float("nan"), "uncertain_fraction": float("nan"),
                "expected_error_fraction": float("nan")}
    return {"uncertainty_mean": float(maps["std"][where].mean()),
            "uncertain_fraction": float((maps["p_wrong"][where] > UNCERTAIN_P_WRONG).mean()),
            "expected_error_fraction": float(maps["p_wrong"].sum() / max(int(np.sum(binary)), 1))}


def calibration_by_decile(p_wrong: np.ndarray, binary: np.ndarray, truth: np.ndarray, n_bins: int = 10) -> np.ndarray:
    """Error rate per uncertainty decile over the support, lowest ``p_wrong`` first, ``(n_bins,)``.

    Support voxels are ranked by ``p_wrong`` and split into ``n_bins`` groups of equal size; each
    group's value is the fraction of its voxels whose binary call differs from ``truth`` (bool).
    Voxels of equal ``p_wrong`` share one rank: a group holding part of such a tie counts each of
    them at the tie's own error rate (the mean over every order of the tie), so the deciles do not
    depend on the voxels' order in the volume (hard votes leave most ``p_wrong`` at exactly 0).
    A calibrated uncertainty gives a rising sequence.
    """
    binary, truth = np.asarray(binary, bool), np.asarray(truth, bool)
    where = support(binary) | truth
    p = np.asarray(p_wrong)[where]
    order = np.argsort(p, kind="stable")
    _, tie, count = np.unique(p[order], return_inverse=True, return_counts=True)
    wrong = np.bincount(tie, weights=(binary != truth)[where][order]) / count  # error rate of each tie
    return np.array([part.mean() if part.size else float("nan") for part in np.array_split(wrong[tie], n_bins)])


def sure_error_rate(p_wrong: np.ndarray, binary: np.ndarray, truth: np.ndarray,
                    sure: float = SURE_P_WRONG) -> tuple[float, int, int]:
    """How often the voxels the map calls sure are wrong: over the voxels :func:`calibration_by_decile` scores (the
    support and the true object), those with ``p_wrong < sure``; their error rate against ``truth`` (bool,
    ``grid.shape``; NaN when no voxel is sure), their number and how many of them are wrong. A calibrated map keeps
    the rate below ``sure`` (below its own mean ``p_wrong`` there, on average); well above it the map is certain
    where the shape is wrong."""
    binary, truth = np.asarray(binary, bool), np.asarray(truth, bool)
    where = (support(binary) | truth) & (np.asarray(p_wrong) < sure)
    n_sure, n_wrong = int(where.sum()), int((binary != truth)[where].sum())
    return (n_wrong / n_sure if n_sure else float("nan")), n_sure, n_wrong


def uncertainty(reconstruction: Reconstruction, measurement: DipMeasurement, operator: DipOperator | None = None,
                **options) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per-voxel maps (:func:`voxel_maps`) and their summary (:func:`summarise`) in one call;
    ``options`` go to :func:`fit_posterior`."""
    maps = voxel_maps(reconstruction, fit_posterior(reconstruction, measurement, operator, **options))
    return maps, summarise(maps, reconstruction.binary)


def resample(volume: torch.Tensor, shape: tuple[int, ...], mode: str) -> np.ndarray:
    """``volume`` resampled to ``shape`` (``area``: block means; else linear interpolation), float64."""
    if tuple(volume.shape) == tuple(shape):
        return volume.double().numpy()
    x = volume.double()[None, None]
    out = F.interpolate(x, size=shape, mode=mode) if mode == "area" else \
        F.interpolate(x, size=shape, mode=mode, align_corners=False)
    return out[0, 0].numpy()
