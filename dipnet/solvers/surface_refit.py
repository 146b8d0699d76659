"""A voxel result's surface refitted to the dips, vertex by vertex, when the data license it.

A 64^3 voxel model explains exact dips only to 0.5-1 % (its own error: uniform-density voxels, a soft
level surface), while the dips of a closed mesh are exact (:mod:`dipnet.operators.mesh_slabs`). So the
marching-cubes surface of a result is taken as a mesh and its vertices moved by Adam to fit the measured
slab volumes, under a small umbrella-Laplacian smoothness term (``smoothness`` x the mean squared
Laplacian of the vertices, mm^2). The topology stays the result's: the refit moves the surface by
fractions of a voxel, it does not open holes or close them.

When the refit may run, and how far, is decided by the data. With a stated noise (the measurement's sigma), by the
discrepancy principle: a result whose dips already agree with the measured ones within that noise (its misfit at
most the noise's own mean plus 3 standard deviations) is kept, since fitted closer the surface would fit the noise;
otherwise the surface is fitted until its misfit reaches the noise's, no closer (or for ``steps``). The misfit
weighs the slabs' errors as a level sensor makes them (``white_share``, default): differences of cumulative
readings, so a profile's low frequencies, its running total, count at the readings' precision. On simulated 30 dB
scans the voxel results' surfaces agree with the dips within independent slab errors (0.4-0.5 x the noise's, as the
truth's own surface) while their running totals are 1.1-7.4 x the readings' noise off (the truth's: 1.05-1.08);
refitted under that model five validation meshes gained 1.3-4 % and the held-out generated shapes 0.1-0.7 %. Under
that model the fit is regularised rather than stopped (``normal_tv``, the default): it runs all its steps with the
total variation of the surface's unit normals as a second term, weighted from the noise's expected misfit, which
charges the noise's bumps and spares flat faces and creases; its misfit ends near the noise's (0.85-1.05 of it on
the validation cases), and five validation meshes gained 3.5-11.3 %, two held-out generated shapes 5.7 and 11.4 %
(weight 50; at 30 and 100 five gained 3.5-9.4 % and 5.9-15.8 %; the discrepancy stop: 0-4 %). Profiles smoothed in
preprocessing are no readings' differences, and their sigma gives no level to stop at: they are weighed as
independent slabs and decided as without a stated noise. Without a stated noise, with dips held out (every
``holdout_every``-th), a probe fits the other dips for ``probe_steps`` steps, and the refit runs (for ``steps``)
only when the held-out dips' misfit fell by ``min_gain`` (10 %) of its start and was still falling at the probe's
end (its lowest point at or after ``still_falling`` (3/4) of the probe). On the validation meshes, noise-free, it
fell by 45-77 % with its lowest point at steps 48-49 of 50; at 30 dB with the noise unstated by 0-14 %, lowest at
steps 2-9, after which it rose as the surface took in the noise. A face the last step leaves folded over (its normal
turned against the start's: a surface that intersects itself is no solid's) has its corners moved to their
neighbours' mean until none is (one face on the penguin, untangled in one pass; eight on a public dinosaur, in 31;
their Chamfer unchanged; folds that come and go on the way, as on most meshes in the first steps, are left to the
fit); a surface still folded after ``unfold_passes`` passes, or a refit that ends no closer to the dips (under
``normal_tv``: and outside the noise's misfit), keeps the start.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import torch
import trimesh
from tqdm.auto import tqdm

from dipnet.core.counts import is_real, whole_number
from dipnet.core.reconstruction import Reconstruction
from dipnet.operators.mesh_slabs import mesh_slab_volumes
from dipnet.shapes.isosurface import volume_to_mesh
from dipnet.solvers.base import SIGMA_FLOOR, SMOOTHED_NOISE_MODEL
from dipnet.solvers.noise_covariance import correlated_precision
from dipnet.solvers.progress import stop_bar

log = logging.getLogger(__name__)

#: The width below which :meth:`_Fit.normal_variation` is quadratic in the normals' difference (a unit vector's:
#: about 3 deg), so that it is smooth where adjacent faces agree.
NORMAL_TV_EPS = 0.05


@dataclass(frozen=True)
class SurfaceRefit:
    """Options of the surface refit (module docstring).

    Args:
        steps: Adam steps of the refit on every dip.
        lr: Adam's step, mm (a vertex moves about this far per step at first).
        smoothness: weight of the mean squared umbrella Laplacian of the vertices (mm^2) against the relative
            data misfit ``sum (predicted - measured)^2 / sum measured^2`` (weighted by ``1 / sigma^2`` when the
            noise is stated).
        holdout_every: every this-th dip is held out in the probe; fewer than two held-out dips skip the refit.
        probe_steps: steps of the probe on the other dips.
        min_gain: the share by which the held-out dips' misfit must fall in the probe for the refit to run.
        still_falling: the share of the probe's steps at or after which the held-out misfit's lowest point must
            come (it must still be falling at the probe's end: noise shows as a turn early in the probe).
        unfold_passes: passes that move the corners of faces the refit left folded over to their neighbours' mean;
            a surface still folded after them is not taken.
        white_share: with a stated noise, the slabs' errors are weighed as differences of cumulative readings
            (:func:`~dipnet.solvers.noise_covariance.correlated_precision`) with a white part of this many
            ``sigma^2 / 2``; ``None``: as independent slabs.
        normal_tv: with a stated noise weighed as the readings' differences, the weight of the total variation of
            the surface's unit normals (the mean over adjacent faces of ``sqrt(|n_a - n_b|^2 + eps^2) - eps``,
            :data:`NORMAL_TV_EPS`) in units of the noise's expected relative misfit: the refit then runs all
            ``steps`` under it (a regularised fit, flat faces and edges kept, the noise's bumps not) instead of
            stopping at the noise's misfit; 0: the discrepancy stop.
    """

    steps: int = 150
    lr: float = 0.03
    smoothness: float = 3e-4
    holdout_every: int = 8
    probe_steps: int = 50
    min_gain: float = 0.1
    still_falling: float = 0.75
    unfold_passes: int = 100
    white_share: float | None = 0.001
    normal_tv: float = 50.0

    def __post_init__(self) -> None:
        for name, low in (("steps", 1), ("holdout_every", 2), ("probe_steps", 1), ("unfold_passes", 0)):
            object.__setattr__(self, name, whole_number(f"surface_refit.{name}", getattr(self, name), low))
        for name, span, inside in (("lr", "(0, inf)", lambda x: 0 < x < math.inf),
                                   ("smoothness", "[0, inf)", lambda x: 0 <= x < math.inf),
                                   ("normal_tv", "[0, inf)", lambda x: 0 <= x < math.inf),
                                   ("min_gain", "[0, 1)", lambda x: 0 <= x < 1),
                                   ("still_falling", "[0, 1]", lambda x: 0 <= x <= 1),
                                   ("white_share", "(0, inf) or null", lambda x: 0 < x < math.inf)):
            value = getattr(self, name)
            if name == "white_share" and value is None:
                continue
            if not is_real(value) or not inside(float(value)):
                raise ValueError(f"surface_refit.{name} must be a number in {span}, got {value!r}")

    @classmethod
    def from_options(cls, options: Any) -> "SurfaceRefit":
        """The refit of a config's ``surface_refit`` mapping (``{}``: the defaults). Anything else, or an option it
        does not take, raises a ``ValueError`` naming the options it takes."""
        names = [f.name for f in fields(cls)]
        if not isinstance(options, Mapping):
            raise ValueError(f"surface_refit must be null (off) or a mapping of its options ({{}} for the defaults: "
                             f"{', '.join(names)}), got {options!r}")
        unknown = sorted(set(options) - set(names))
        if unknown:
            raise ValueError(f"surface_refit takes {', '.join(names)}; not {', '.join(map(str, unknown))}")
        return cls(**options)

    def refit(self, recon: Reconstruction, target: torch.Tensor, sigma: torch.Tensor | None,
              directions: torch.Tensor, edges: torch.Tensor, progress: bool = False,
              differenced: bool = True) -> Reconstruction:
        """``recon`` with :attr:`~Reconstruction.mesh` refitted to ``target`` when the data license it, and
        ``info["surface_refit"]`` recording the decision, the misfits and the mesh's volume either way.

        Args:
            recon: a 3D result; its surface is ``occupancy == threshold``.
            target: measured slab volumes ``(K, M)``, mm^3, on the slabs ``edges``.
            sigma: their noise sigma ``(K, M)`` mm^3, or ``None``.
            directions: ``(K, 3)`` unit "up" vectors; edges: ``(M + 1,)`` slab boundaries, mm.
            differenced: whether the slabs are the differences of cumulative readings as read; profiles smoothed
                in preprocessing (``metadata["smoothed"]``) are not: their errors are weighed as independent, and
                held-out dips decide as without a stated noise (their sigma gives the fit no level to stop at).

        Raises:
            ValueError: ``target`` or ``sigma`` holds a NaN or infinite value.
        """
        for name, values in (("measured slab volumes", target), ("slab sigma", sigma)):
            bad = 0 if values is None else int((~torch.isfinite(values)).sum())
            if bad:  # else the probe read a NaN misfit as "fell by 0.0%: would fit the noise", or ran on NaN
                raise ValueError(f"surface refit: the {name} hold {bad} NaN or infinite value(s) of {values.numel()}: "
                                 "repair or drop those dips (dipnet.validate_measurement names them)")
        started = time.perf_counter()
        record: dict = {"applied": False, **asdict(self)}
        recon.info["surface_refit"] = record
        if sigma is not None and not bool((sigma > 0).any()):
            sigma = None  # a sigma of 0 everywhere states no noise
        if recon.grid.ndim != 3:
            record["reason"] = "3D only: a 2D result keeps its contours"
            return recon
        mesh = volume_to_mesh(recon.occupancy.detach().cpu().numpy(), recon.grid, recon.threshold)
        held = torch.arange(len(directions)) % self.holdout_every == 0
        if len(mesh.faces) == 0 or ((sigma is None or not differenced) and int(held.sum()) < 2):  # (the probe's)
            record["reason"] = ("the result has no surface" if len(mesh.faces) == 0 else
                                f"{len(directions)} dips hold out fewer than 2 at every {self.holdout_every}-th")
            return recon
        fit = _Fit(mesh, target, sigma, directions, edges, self.smoothness, self.white_share, differenced)
        measured_volume = float(target.sum(1).median())
        start_slabs = fit.slabs(fit.start)
        record["residual_before"] = fit.residual(start_slabs)
        regularised = fit.precision is not None and self.normal_tv > 0  # a stated noise, the readings model
        if sigma is not None:
            record.update(noise_model=fit.noise_model, noise_ratio=fit.noise_ratio(start_slabs))
            limit = fit.noise_limit()
            if regularised:
                fit.tv_weight = self.normal_tv * fit.noise_relative_misfit()
                record["normal_tv_weight"] = fit.tv_weight
            elif record["noise_ratio"] <= limit:
                record["reason"] = (f"the result's dips agree with the measured ones within their stated noise "
                                    f"({fit.noise_model} model: misfit {record['noise_ratio']:.2f} x the noise's, at "
                                    f"most {limit:.2f}: the noise's own 1 plus 3 standard deviations): a surface "
                                    "fitted closer would fit the noise, so its surface is kept")
                return self._finish(recon, mesh, record, started, measured_volume)
        every = torch.ones_like(held)
        probe = sigma is None or not differenced  # a smoothed profile's sigma gives no level to stop at: held-out dips
        with tqdm(total=self.steps + (self.probe_steps if probe else 0), desc="surface refit",
                  disable=not progress, leave=False) as bar:
            if probe:
                why_kept = self._probe(fit, held, record, bar)
                if why_kept:
                    record["reason"] = why_kept
                    stop_bar(bar, "surface kept")
                    return self._finish(recon, mesh, record, started, measured_volume)
                vertices = fit.start.clone()
                for _step, _slabs in fit.descend(vertices, every, self.steps, self.lr, bar):
                    pass
                why = (f"the held-out dips' misfit fell by {record['heldout_gain']:.1%} in the probe and was still "
                       f"falling at its end (lowest at step {record['heldout_best_step']} of {self.probe_steps})")
            elif regularised:  # the normals' variation, weighed against the noise's misfit, keeps it from the noise
                vertices = fit.start.clone()
                for _step, _slabs in fit.descend(vertices, every, self.steps, self.lr, bar):
                    pass
                record["steps_run"] = self.steps
                why = (f"its misfit was {record['noise_ratio']:.2f} x the stated noise's ({fit.noise_model} model); "
                       f"the surface was fitted to the dips for {self.steps} steps under the total variation of its "
                       f"normals, weighted {self.normal_tv:g} x the noise's expected relative misfit")
            else:  # the discrepancy principle: fitted until the dips' misfit is the noise's, no closer
                vertices, ran = fit.start.clone(), self.steps
                for step, slabs in fit.descend(vertices, every, self.steps, self.lr, bar):
                    if fit.noise_ratio(slabs) <= 1.0:
                        ran = step - 1
                        break
                record["steps_run"] = ran
                why = (f"its misfit was {record['noise_ratio']:.2f} x the stated noise's ({fit.noise_model} model; "
                       f"above {limit:.2f}), so the surface was fitted to the dips "
                       + (f"until their misfit reached the noise's ({ran} of {self.steps} steps)" if ran < self.steps
                          else f"for {self.steps} steps, the most it may take"))
        return self._take(recon, mesh, fit, vertices, why, record, started, measured_volume, regularised)

    def _probe(self, fit: "_Fit", held: torch.Tensor, record: dict, bar: tqdm) -> str | None:
        """Fit the dips not ``held`` for :attr:`probe_steps` from the start; record the held-out dips' misfit and
        return why the surface is kept (``None``: the refit may run)."""
        probe, best, best_step, held_start = fit.start.clone(), math.inf, 0, math.nan
        for step, slabs in fit.descend(probe, ~held, self.probe_steps, self.lr, bar):
            held_now = float(fit.relative_misfit(slabs, held))  # of the vertices before this step
            held_start = held_now if step == 1 else held_start
            if held_now < best:
                best, best_step = held_now, step - 1
        gain = 1.0 - best / held_start if held_start > 0 else 0.0
        record.update(heldout_dips=int(held.sum()), heldout_residual_before=held_start ** 0.5,
                      heldout_residual_best=best ** 0.5, heldout_best_step=best_step, heldout_gain=gain)
        if gain >= self.min_gain and best_step >= self.still_falling * self.probe_steps:
            return None
        why = (f"less than min_gain={self.min_gain:g}" if gain < self.min_gain else
               f"but it turned up after step {best_step} of {self.probe_steps} (still_falling="
               f"{self.still_falling:g})")
        return (f"the held-out dips' misfit fell by {gain:.1%} in the probe, {why}: a surface "
                "fitted closer would fit the dips' noise, not the shape, so its surface is kept")

    def _take(self, recon: Reconstruction, mesh: trimesh.Trimesh, fit: "_Fit", vertices: torch.Tensor, why: str,
              record: dict, started: float, measured_volume: float, regularised: bool = False) -> Reconstruction:
        """``recon`` with the refitted ``vertices`` as its mesh, unless folds they leave cannot be undone or they
        end no closer to the dips than the start (then its surface is kept, with a warning); ``why``: why the refit
        ran; ``regularised``: under :attr:`normal_tv`, where a surface that ends within the noise's misfit (its
        mean and 3 standard deviations) is taken too (a start that fitted the noise may end further off)."""
        folded = int(fit.folded(vertices).sum())  # a fold may come and go on the way: the last step's counts
        if folded:
            passes, left = fit.unfold(vertices, self.unfold_passes)
            record.update(folded_faces=folded, unfolded_in=passes, folded_left=left)
            if left:
                record["reason"] = (f"the refit's last step left {folded} faces folded over (their normals "
                                    f"turned against the start's) and {passes} passes of moving their corners "
                                    f"to their neighbours' mean left {left}: a surface that intersects itself "
                                    "is no solid's, so the surface is kept")
                log.warning("surface refit: %s", record["reason"])
                return self._finish(recon, mesh, record, started, measured_volume)
        after = fit.slabs(vertices)
        residual = fit.residual(after)
        unfolded = (f"; the {folded} faces its last step folded over were unfolded by moving their corners "
                    f"to their neighbours' mean ({passes} passes)") if folded else ""
        if residual < record["residual_before"] or (regularised and fit.noise_ratio(after) <= fit.noise_limit()):
            recon.mesh = trimesh.Trimesh(vertices.numpy(), mesh.faces, process=False)
            record.update(applied=True, residual_after=residual, reason=f"{why}{unfolded}")
            if "noise_ratio" in record:
                record["noise_ratio_after"] = fit.noise_ratio(after)
        else:  # a fit that ends no closer to the dips than it began has gone wrong: keep the surface
            record["reason"] = (f"the refit ended no closer to the dips than it began (relative residual "
                                f"{record['residual_before']:.3g} -> {residual:.3g}"
                                + (", outside the noise's misfit" if regularised else "")
                                + f"){unfolded}, so the surface is kept")
            log.warning("surface refit: %s", record["reason"])
        return self._finish(recon, mesh, record, started, measured_volume)

    @staticmethod
    def _finish(recon: Reconstruction, mesh: trimesh.Trimesh, record: dict, started: float,
                measured_volume: float) -> Reconstruction:
        """``recon`` with the volume of its surface (refitted or kept), that over the ``measured_volume`` (mm^3: the
        median of the profiles' totals) and the time in ``record``, logged."""
        record["mesh_volume_mm3"] = abs(float((mesh if recon.mesh is None else recon.mesh).volume))
        record["volume_ratio"] = record["mesh_volume_mm3"] / measured_volume if measured_volume > 0 else math.nan
        record["seconds"] = time.perf_counter() - started
        log.info("surface refit: %s (relative residual %.3g%s)", record["reason"], record["residual_before"],
                 f" -> {record['residual_after']:.3g}" if record["applied"] else "")
        return recon


def without_surface_refit(solver: Any) -> Any:
    """``solver`` itself when it refits no surface, else a copy that does not: for the solves whose occupancy alone
    is read (the adaptive loop's after every batch), which the refit's mesh would only slow (tens of seconds at
    64^3)."""
    if getattr(solver, "surface_refit", None) is None:
        return solver
    quiet = copy.copy(solver)
    quiet.surface_refit = None
    return quiet


class _Fit:
    """The refit's objective on one mesh: data misfit per dip subset and smoothness."""

    def __init__(self, mesh: trimesh.Trimesh, target: torch.Tensor, sigma: torch.Tensor | None,
                 directions: torch.Tensor, edges: torch.Tensor, smoothness: float,
                 white_share: float | None = None, differenced: bool = True) -> None:
        self.start = torch.tensor(mesh.vertices, dtype=torch.float64)
        self.faces = torch.tensor(mesh.faces, dtype=torch.long)
        self.start_normals = self.normals(self.start)
        self.target, self.directions, self.edges = target.double(), directions.double(), edges.double()
        if sigma is not None:
            sigma = sigma.double().clamp_min(SIGMA_FLOOR * float(sigma[sigma > 0].median()))
        self.weight = torch.ones_like(self.target) if sigma is None else sigma.pow(-2)
        # the noise's own score of the misfit's numerator, its mean and standard deviation: independent slabs
        # score one per slab (chi-square), the readings model what correlated_precision states
        self.precision: torch.Tensor | None = None
        self.noise_mean, self.noise_sd = float(self.target.numel()), (2.0 * self.target.numel()) ** 0.5
        self.noise_model = "independent"
        if sigma is not None and white_share is not None and not differenced:
            self.noise_model = SMOOTHED_NOISE_MODEL
        elif sigma is not None and white_share is not None:
            try:
                noise = correlated_precision(self.target, sigma, white_share)
            except ValueError:  # too large a problem for the (K, M, M) precision
                self.noise_model = f"independent, the readings model's {tuple(self.target.shape)} slabs being too many"
            else:
                self.precision, self.noise_model = noise.precision, "readings"
                self.noise_mean, self.noise_sd = noise.expected, noise.variance ** 0.5
        self.smoothness = float(smoothness)
        average = trimesh.smoothing.laplacian_calculation(mesh, equal_weight=True).tocoo()  # neighbours' mean
        index = np.concatenate([np.stack([average.row, average.col]),
                                np.tile(np.arange(len(mesh.vertices)), (2, 1))], 1)
        values = np.concatenate([-average.data, np.ones(len(mesh.vertices))])
        self.laplacian = torch.sparse_coo_tensor(torch.from_numpy(index), torch.from_numpy(values),
                                                 (len(mesh.vertices),) * 2, check_invariants=False).coalesce()
        self.adjacent = torch.from_numpy(np.array(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2))
        self.tv_weight = 0.0  # of normal_variation, set by SurfaceRefit.refit under normal_tv

    def misfit(self, slabs: torch.Tensor, dips: torch.Tensor) -> torch.Tensor:
        """The noise-weighted squared residual of ``slabs`` (K, M) over the dips ``dips`` (bool ``(K,)``):
        ``sum w r^2`` with independent slabs, ``sum_k r_k^T P_k r_k`` under the readings model."""
        residual = slabs[dips] - self.target[dips]
        if self.precision is None:
            return (self.weight[dips] * residual.pow(2)).sum()
        return torch.einsum("km,kmn,kn->", residual, self.precision[dips], residual)

    def relative_misfit(self, slabs: torch.Tensor, dips: torch.Tensor) -> torch.Tensor:
        """:meth:`misfit` over ``sum w target^2`` on the dips ``dips`` (bool ``(K,)``) of ``slabs`` (K, M)."""
        w, t = self.weight[dips], self.target[dips]
        return self.misfit(slabs, dips) / (w * t.pow(2)).sum().clamp_min(1e-300)

    def slabs(self, vertices: torch.Tensor) -> torch.Tensor:
        """The slab volumes ``(K, M)`` of ``vertices`` (no gradient), mm^3."""
        with torch.no_grad():
            return mesh_slab_volumes(vertices, self.faces, self.directions, self.edges)

    def residual(self, slabs: torch.Tensor) -> float:
        """Relative residual of ``slabs`` on every dip: the square root of :meth:`relative_misfit`."""
        return float(self.relative_misfit(slabs, torch.ones(len(self.directions), dtype=torch.bool))) ** 0.5

    def normals(self, vertices: torch.Tensor) -> torch.Tensor:
        """The faces' normals scaled by twice their areas ``(F, 3)``, mm^2."""
        with torch.no_grad():
            corners = vertices[self.faces]
            return torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])

    def folded(self, vertices: torch.Tensor) -> torch.Tensor:
        """Which faces of ``vertices`` have turned round against the start (their normal points against the
        start's), where the surface has folded over and intersects itself: bool ``(F,)``."""
        return (self.normals(vertices) * self.start_normals).sum(1) < 0

    def unfold(self, vertices: torch.Tensor, passes: int) -> tuple[int, int]:
        """Move the corners of folded faces (:meth:`folded`) of ``vertices`` (in place) to the mean of their
        neighbours, pass by pass, until none is folded or ``passes`` are done: ``(passes done, faces still folded)``."""
        with torch.no_grad():
            for done in range(passes + 1):
                folded = self.folded(vertices)
                if done == passes or not bool(folded.any()):
                    return done, int(folded.sum())
                corners = torch.unique(self.faces[folded])
                vertices[corners] = (vertices - torch.sparse.mm(self.laplacian, vertices))[corners]

    def noise_ratio(self, slabs: torch.Tensor) -> float:
        """:meth:`misfit` of ``slabs`` on every dip over the noise's own (a stated sigma; 1: the noise's mean;
        independent slabs: the mean of ``(slabs - measured)^2 / sigma^2``)."""
        return float(self.misfit(slabs, torch.ones(len(self.directions), dtype=torch.bool))) / self.noise_mean

    def noise_relative_misfit(self) -> float:
        """The noise's expected :meth:`relative_misfit` on every dip (its mean misfit over ``sum w target^2``)."""
        return self.noise_mean / float((self.weight * self.target.pow(2)).sum().clamp_min(1e-300))

    def normal_variation(self, vertices: torch.Tensor) -> torch.Tensor:
        """The total variation of the unit face normals of ``vertices``: the mean over adjacent faces of
        ``sqrt(|n_a - n_b|^2 + eps^2) - eps`` (:data:`NORMAL_TV_EPS`; 0 for a plane), differentiable."""
        corners = vertices[self.faces]
        normals = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-12)
        if len(self.adjacent) == 0:
            return normals.new_zeros(())
        step = (normals[self.adjacent[:, 0]] - normals[self.adjacent[:, 1]]).pow(2).sum(1)
        return ((step + NORMAL_TV_EPS ** 2).sqrt() - NORMAL_TV_EPS).mean()

    def noise_limit(self) -> float:
        """The largest :meth:`noise_ratio` the noise itself gives: its mean and 3 standard deviations, over its mean
        (independent slabs: ``1 + 3 sqrt(2 / slabs)``)."""
        return 1.0 + 3.0 * self.noise_sd / self.noise_mean

    def descend(self, vertices: torch.Tensor, dips: torch.Tensor, steps: int, lr: float, bar: tqdm):
        """Move ``vertices`` (in place) by ``steps`` Adam steps on the dips ``dips``; yield each step's number and the
        slab volumes of every dip (detached) of the vertices before that step, which it then takes (a caller that
        stops iterating keeps the vertices it was shown): held-out dips cost no extra pass."""
        vertices.requires_grad_(True)
        optimiser = torch.optim.Adam([vertices], lr=lr)
        try:
            for step in range(1, steps + 1):
                optimiser.zero_grad()
                slabs = mesh_slab_volumes(vertices, self.faces, self.directions, self.edges)
                smooth = torch.sparse.mm(self.laplacian, vertices).pow(2).sum(1).mean()
                loss = self.relative_misfit(slabs, dips) + self.smoothness * smooth
                if self.tv_weight:
                    loss = loss + self.tv_weight * self.normal_variation(vertices)
                loss.backward()
                yield step, slabs.detach()
                optimiser.step()
                bar.update()
        finally:
            vertices.requires_grad_(False)
