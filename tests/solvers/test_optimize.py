"""support_hull by column intervals (the same mask as testing every voxel against every slab), and the
data term under the correlated noise of cumulative readings."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.reconstruction import Reconstruction
from dipnet.operators import make_operator
from dipnet.shapes import Disk
from dipnet.simulator.physics import LevelSensor
from dipnet.simulator.simulate import simulate_measurement
from dipnet.solvers import noise_covariance, optimize
from dipnet.solvers.base import SMOOTHED_NOISE_MODEL
from dipnet.solvers.noise_covariance import filled_span
from dipnet.solvers.optimize import DataTerm, slab_support, support_hull
from dipnet.solvers.voxel import VoxelSolver
from dipnet.solvers.weights import noise_level


def brute_force_hull(target, grid, directions, edges, rel_tol, margin):
    """The reference: every voxel centre tested against every orientation's slab range."""
    lo, hi = slab_support(target, edges, rel_tol, margin * grid.voxel_size)
    t = grid.centers(target.dtype).reshape(-1, grid.ndim) @ directions.to(target.dtype).T  # (voxels, K)
    inside = ((t >= lo) & (t <= hi)).all(dim=1).reshape(grid.shape)
    return inside & grid.working_mask()


def directions_with_flat_ones(ndim: int, k: int, seed: int) -> torch.Tensor:
    """Random unit directions plus the axes and directions with no last component (theta_z = 0)."""
    gen = torch.Generator().manual_seed(seed)
    rand = torch.randn(k, ndim, generator=gen, dtype=torch.float64)
    flat = torch.randn(3, ndim, generator=gen, dtype=torch.float64)
    flat[:, -1] = 0.0
    axes = torch.cat([torch.eye(ndim, dtype=torch.float64), -torch.eye(ndim, dtype=torch.float64)])
    dirs = torch.cat([rand, flat, axes])
    return dirs / dirs.norm(dim=1, keepdim=True)


def ball_profiles(grid: Grid, directions: torch.Tensor, centre: torch.Tensor, radius: float, m: int):
    """Slab volumes ``(K, m)`` of a ball (exact slab integrals of its cross-section) and the edges."""
    edges = torch.linspace(-grid.extent / 2, grid.extent / 2, m + 1, dtype=torch.float64)
    offset = directions @ centre  # (K,) the ball's centre height per direction
    u = (edges[None, :] - offset[:, None]).clamp(-radius, radius)  # heights relative to the centre
    if grid.ndim == 3:  # volume below height u: pi (r^2 u - u^3/3)
        below = math.pi * (radius**2 * u - u**3 / 3)
    else:  # area below u: u sqrt(r^2 - u^2) + r^2 asin(u / r)
        below = u * (radius**2 - u**2).clamp(min=0).sqrt() + radius**2 * torch.asin(u / radius)
    return below.diff(dim=1), edges


@pytest.mark.parametrize("ndim,n,margin", [(2, 40, 1.5), (2, 33, 0.0), (3, 20, 1.5), (3, 17, 3.0)])
def test_column_hull_equals_the_brute_force_mask(ndim, n, margin):
    grid = Grid(n, ndim, 100.0)
    dirs = directions_with_flat_ones(ndim, 25, seed=n)
    centre = torch.tensor([8.0, -5.0, 3.0][:ndim], dtype=torch.float64)
    target, edges = ball_profiles(grid, dirs, centre, 22.0, m=n)
    expected = brute_force_hull(target, grid, dirs, edges, 0.005, margin)
    for chunk in (None, 1, 7):
        got = support_hull(target, grid, dirs, edges, 0.005, margin, chunk=chunk)
        assert torch.equal(got, expected)
    assert 0 < int(expected.sum()) < int(grid.working_mask().sum())  # the slabs did cut the ball


def test_a_flat_direction_that_misses_a_column_empties_it():
    # theta = +x only: the slab support [lo, hi] in x keeps whole columns inside it and none outside
    grid = Grid(16, 3, 100.0)
    dirs = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    edges = torch.linspace(-50, 50, 17, dtype=torch.float64)
    target = torch.zeros(1, 16, dtype=torch.float64)
    target[0, 6:9] = 1.0  # material between x = -12.5 and 6.25 mm
    hull = support_hull(target, grid, dirs, edges, 0.005, margin=0.0)
    x = grid.axis()
    keep = (x >= edges[6]) & (x <= edges[9])
    assert torch.equal(hull, keep[None, None, :].expand(grid.shape) & grid.working_mask())


def test_a_solver_given_dips_that_share_no_voxel_says_so():
    """Profiles that put the object in two places at once (up: 20-25 mm above the centre; down: 20-25 mm
    below it, as far-off start heights do): the support hull is empty; one named error, no ZeroDivisionError."""
    from dipnet.solvers.optimize import EmptySupportError

    grid = Grid(16, extent=60.0)
    profiles = np.zeros((2, 16))
    profiles[:, 13:15] = 100.0  # slabs at 22.5-30 mm along each direction
    m = DipMeasurement(directions=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), profiles=profiles,
                       slab_thickness=grid.voxel_size, offsets=np.full(2, -30.0))
    with pytest.raises(EmptySupportError, match="calibrate the rig geometry"):
        VoxelSolver(iterations=5, progress=False).solve(m, make_operator(grid, m.directions, grid.n))


def test_a_diverging_optimisation_is_one_named_user_error():
    """A loss that becomes infinite (here at the second step: the occupancy ``exp(1000 x)`` from ``x = -0.01``,
    after Adam's first step of the learning rate 1 up where the disc is) raises ``DivergedError``, a
    ``ValueError`` (one ``error:`` line on the command line) naming the stage, the step and the learning rate."""
    op, occ, target, _ = correlated_problem()
    x = torch.full_like(occ, -0.01, requires_grad=True)
    with pytest.raises(ValueError, match=r"my stage: the loss became (inf|nan) at step 2 of 9 \(learning rate 1\)"
                       r".*diverged; try a lower solver.lr") as err:
        optimize.optimise([x], lambda: (1e3 * x).exp(), DataTerm(op, target), [], iterations=9, lr=1.0,
                          progress=False, desc="my stage")
    assert isinstance(err.value, optimize.DivergedError)


def correlated_problem(seed: int = 0):
    """A 2D operator, a disc's occupancy and profiles ``g`` (empty slabs at both ends), slab sigmas."""
    grid = Grid(16, 2)
    gen = torch.Generator().manual_seed(seed)
    dirs = torch.randn(5, 2, generator=gen, dtype=torch.float64)
    op = make_operator(grid, dirs / dirs.norm(dim=1, keepdim=True), 24)
    occ = (grid.centers(torch.float64).norm(dim=-1) < 0.3 * grid.extent).double()
    target = op(occ)
    sigma = (0.02 + 0.01 * torch.rand(target.shape, generator=gen, dtype=torch.float64)) * target.max()
    return op, occ, target, sigma


def reference_covariance(sigma: torch.Tensor, span: torch.Tensor, white_share: float) -> torch.Tensor:
    """One profile's covariance built slab by slab: inside the span, slab ``j`` is ``e_j - e_(j-1)``
    with independent edge errors ``e`` of variance ``sigma_j^2 / 2`` (none below the span's first
    slab) plus white noise ``white_share sigma_j^2 / 2``; outside it, independent ``sigma_j^2``."""
    m = len(sigma)
    cov = torch.zeros(m, m, dtype=torch.float64)
    for i in range(m):
        for j in range(m):
            if not (span[i] and span[j]):
                cov[i, j] = sigma[i] ** 2 if i == j else 0.0
                continue
            edge = lambda n: sigma[n] ** 2 / 2 if n >= 0 and span[n] else 0.0  # noqa: E731
            if i == j:
                cov[i, j] = edge(i) + edge(i - 1) + white_share * sigma[i] ** 2 / 2
            elif abs(i - j) == 1:
                cov[i, j] = -edge(min(i, j))
    return cov


@pytest.mark.parametrize("white_share", [1e-6, 0.25, 1.0])
def test_correlated_term_is_generalised_least_squares(white_share):
    op, occ, target, sigma = correlated_problem()
    data = DataTerm(op, target, sigma, dtype=torch.float64, noise_model="correlated", white_share=white_share)
    guess = occ * (0.7 + 0.5 * torch.rand(occ.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64))
    r = op(guess) - target
    span = filled_span(target)
    expected = sum(float(r[k] @ torch.linalg.solve(reference_covariance(sigma[k], span[k], white_share), r[k]))
                   for k in range(len(r)))
    norm = float((sigma ** -2 * target ** 2).sum())
    assert float(data(guess)) == pytest.approx(expected / norm, rel=1e-8)
    assert float(data(occ)) == pytest.approx(0.0, abs=1e-20)
    if white_share < 1e-3:  # no white part: the GLS term is the cumulative residual's, edge by edge
        cumulative = torch.cumsum(r, -1)
        assert float(data(guess)) == pytest.approx(float((2 / sigma ** 2 * cumulative ** 2)[span].sum()) / norm,
                                                   rel=1e-3)


def test_correlated_term_expects_what_the_differenced_noise_scores():
    """Measured with the noise the model describes (differences of independent cumulative
    errors), the true occupancy scores :attr:`DataTerm.expected_noise` on average; the
    independent term's noise level is what it expects of independent noise."""
    op, occ, target, sigma = correlated_problem(1)
    span = filled_span(target)
    gen = torch.Generator().manual_seed(2)
    expected = DataTerm(op, target, sigma, dtype=torch.float64, noise_model="correlated").expected_noise
    scores = []
    for _ in range(300):
        edge = torch.randn(target.shape, generator=gen, dtype=torch.float64) * sigma / math.sqrt(2) * span
        noisy = target + torch.diff(edge, dim=-1, prepend=torch.zeros_like(edge[:, :1]))
        scores.append(float(DataTerm(op, noisy, sigma, dtype=torch.float64, noise_model="correlated")(occ)))
    assert np.mean(scores) == pytest.approx(expected, rel=0.07)
    level = noise_level(target, sigma, DataTerm(op, target, sigma).weight)[0]
    assert expected < level  # the white part takes a share of the noise's variance


def test_correlated_model_needs_sigma_and_a_bounded_problem(monkeypatch):
    op, occ, target, sigma = correlated_problem()
    guess = 0.8 * occ
    plain = DataTerm(op, target, dtype=torch.float64)
    without_sigma = DataTerm(op, target, dtype=torch.float64, noise_model="correlated")
    assert without_sigma.precision is None and float(without_sigma(guess)) == float(plain(guess))
    zeros = torch.zeros_like(sigma)
    assert DataTerm(op, target, zeros, noise_model="correlated").precision is None  # no sigma at all: independent
    partly = sigma.clone()
    partly[0, 8:12] = 0.0  # zeros among known sigmas are floored, as the independent weights are
    assert math.isfinite(float(DataTerm(op, target, partly, dtype=torch.float64, noise_model="correlated")(guess)))
    with pytest.raises(ValueError, match="noise_model"):
        DataTerm(op, target, noise_model="white")
    with pytest.raises(ValueError, match="white_share"):
        DataTerm(op, target, sigma, noise_model="correlated", white_share=0.0)
    with pytest.raises(ValueError, match="white_share must be a finite number"):
        VoxelSolver(white_share=math.inf)  # was: every slab weighed 0 once solving, an empty result with exit 0
    with pytest.raises(ValueError, match="seed must be a whole number"):
        VoxelSolver(seed=1.5)  # was: the seed-1 solve, unsaid
    for tol in (math.nan, math.inf):  # NaN never stopped early, inf stopped after the first window, unsaid
        with pytest.raises(ValueError, match="tol must be a finite number"):
            VoxelSolver(tol=tol)
    with pytest.raises(ValueError, match="noise_model"):
        VoxelSolver(noise_model="cumulative")
    monkeypatch.setattr(noise_covariance, "PRECISION_ENTRIES", 100)
    with pytest.raises(ValueError, match=r"\(5, 24, 24\) precision.*noise_model='independent'"):
        DataTerm(op, target, sigma, noise_model="correlated")


def test_smoothed_profiles_are_weighed_as_independent_slabs_and_the_result_says_so():
    """Profiles smoothed in preprocessing are not the differences of the readings, so ``noise_model="correlated"``
    (which ``solver=voxel_learned`` sets) weighs them as independent slabs, as the surface refit does: the same
    solve as ``"independent"``, its ``info["noise_model"]`` saying why. Before, their smoothed sigma was taken for
    the readings' and the weight rule and rounds compared the data term with a noise the model got wrong."""
    grid = Grid(20, 2, 100.0)
    directions = torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.0, 1.0], [-0.6, 0.8], [-0.8, 0.6]], dtype=torch.float64)
    sensor = LevelSensor(snr_db=30.0, quantum_mm=0.0, seed=3)
    op = make_operator(grid, directions)
    opts = dict(iterations=20, coarse_to_fine=False, progress=False, priors={"tv": {"weight": "auto"}}, seed=1)
    results = {}
    for smooth in (False, True):
        _, meas = simulate_measurement(Disk(30.0), directions, grid=grid, sensor=sensor, smooth=smooth,
                                       progress=False)
        assert meas.sigma is not None and bool(meas.metadata["smoothed"]) == smooth
        results[smooth] = {model: VoxelSolver(noise_model=model, **opts).solve(meas, op)
                           for model in ("independent", "correlated")}
    assert results[False]["correlated"].info["noise_model"] == "correlated"
    assert results[True]["correlated"].info["noise_model"] == SMOOTHED_NOISE_MODEL
    assert results[True]["independent"].info["noise_model"] == "independent"
    assert not torch.equal(results[False]["correlated"].occupancy, results[False]["independent"].occupancy)
    assert torch.equal(results[True]["correlated"].occupancy, results[True]["independent"].occupancy)
    assert results[True]["correlated"].info["weight_rule"] == results[True]["independent"].info["weight_rule"]
    term = DataTerm(op, meas.profiles, meas.sigma, noise_model="correlated", differenced=False)
    assert term.precision is None and term.expected_noise is None and term.noise_model == SMOOTHED_NOISE_MODEL


def test_solver_compares_its_residual_with_the_correlated_noise_expectation():
    op, occ, target, sigma = correlated_problem()
    meas = DipMeasurement(profiles=target, directions=op.directions, slab_thickness=op.slab_thickness,
                          offsets=op.slab_edges()[:1].expand(len(target)), sigma=sigma)
    solver = VoxelSolver(iterations=5, coarse_to_fine=False, progress=False, noise_model="correlated", white_share=0.5)
    recon = solver.solve(meas, op)
    expected = DataTerm(op, target, sigma, noise_model="correlated", white_share=0.5).expected_noise
    record = recon.info["weight_rule"]  # the TV weight's rule compared the residual with this noise
    assert record["noise_source"] == "sigma" and record["noise_residual"] == pytest.approx(expected ** 0.5, rel=1e-6)


def test_a_warm_start_on_other_voxels_is_refused():
    """Before: a Reconstruction of the same shape on another grid (16^3 over 200 mm for the operator's 100 mm) was
    taken voxel by voxel as the start: a chamber box came back at IoU 0.551 (no warm start 0.744, the minnorm
    start on the operator's grid 0.784), without a word."""
    grid, other = Grid(16, 2, 100.0), Grid(16, 2, 200.0)
    directions = torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.0, 1.0], [-0.6, 0.8]], dtype=torch.float64)
    disk = Disk(30.0)
    _, meas = simulate_measurement(disk, directions, grid=grid, progress=False)
    op = make_operator(grid, directions)
    opts = dict(iterations=2, coarse_to_fine=False, progress=False)
    with pytest.raises(ValueError, match=r"warm start is a reconstruction on Grid\(n=16, ndim=2, extent=200.0\), the "
                                         r"operator's grid is Grid\(n=16, ndim=2, extent=100.0\)"):
        VoxelSolver(warm_start=Reconstruction(disk.occupancy(other), other), **opts).solve(meas, op)
    VoxelSolver(warm_start=Reconstruction(disk.occupancy(grid), Grid(16, 2, 100.0)), **opts).solve(meas, op)


@pytest.mark.parametrize("option, value", [("iterations", 2.5), ("iterations", 0), ("window", "25"),
                                           ("iterations", float("inf")), ("lr", "0.1"), ("lr", float("inf")),
                                           ("lr", -0.05)])
def test_counts_that_are_not_whole_and_learning_rates_that_are_not_numbers_are_refused(option, value):
    """Before: ``iterations=2.5`` ran 2 iterations unsaid; ``lr="0.1"`` failed with "'>' not supported between
    instances of 'str' and 'int'"; ``lr=inf`` diverged only once solving."""
    with pytest.raises(ValueError, match=f"{option} must be a"):
        VoxelSolver(**{option: value})
    assert VoxelSolver(iterations=3.0, lr=np.float32(0.1)).iterations == 3
