"""The reconstruction job behind ``scripts/reconstruct.py``: config in, files and metrics out.

Data flow: shape -> measurement (simulated from the shape's own geometry, or read from a
file) -> operator -> solver -> reconstruction -> mesh, volume, metrics and figures, all
written into one output directory.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from dipnet.core.locks import checkpoint_directory_lock
from dipnet.core.warn import log_and_warn
from dipnet.evaluation import consistency, metrics
from dipnet.outputs import export, plots
from dipnet.outputs.progress import OutputStages, planned_stages
from dipnet.outputs.summary import headline, prior_weight_metrics, surface_refit_metrics
from dipnet.shapes.isosurface import volume_to_mesh
from dipnet.jobs.calibration_job import self_calibration_job
from dipnet.jobs.deprecations import upgrade_config
from dipnet.solvers.checkpoint import attach_checkpoint, checkpoint_directory
from dipnet.core.framing import extent_around, smallest_fill
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.strict_json import write_json
from dipnet.core.rawscan import RawScan
from dipnet.operators import backend_name
from dipnet.jobs.options import ConfigError, check_config, check_grid_options, hydra_overrides
from dipnet.core.reconstruction import Reconstruction
from dipnet.jobs.resources import check_memory
from dipnet.shapes import Shape
from dipnet.solvers.base import measured_profiles
from dipnet.jobs.threads import configure_threads
from dipnet.outputs.resolvability import write_resolvability
from dipnet.outputs.uncertainty import write_uncertainty
from dipnet.preprocessing.validation import validate_measurement

log = logging.getLogger(__name__)


@dataclass
class JobResult:
    """What one reconstruction job produced."""

    measurement: DipMeasurement
    reconstruction: Reconstruction
    metrics: dict[str, Any]
    output_dir: Path


def build_grid(cfg: DictConfig, shape: Shape | None, source) -> Grid:
    """The grid from ``ndim``, ``resolution`` and ``extent_mm`` (``null``: chosen around ``shape``,
    see :mod:`dipnet.core.framing`, or the source's own extent); clear errors on bad values."""
    check_grid_options(cfg)
    extent = cfg.extent_mm
    if extent is None and shape is not None:
        extent = extent_around(shape.radius(), int(cfg.resolution), float(cfg.fill))
        low = smallest_fill(shape.radius(), shape.volume, int(cfg.resolution), int(cfg.ndim))
        if cfg.fill < low and low <= 1:  # was refused after the dips, naming an extent_mm the user never set
            raise ConfigError(f"fill must be in [{low:.3g}, 1] for this object at resolution {cfg.resolution} "
                              f"(the share of the working ball its bounding radius fills), got {cfg.fill!r}: the grid "
                              f"chosen around it (extent_mm={extent:.3g}) makes the whole object, "
                              f"{shape.volume:.4g} {'mm^3' if int(cfg.ndim) == 3 else 'mm^2'}, less than one voxel")
    elif extent is None:
        extent = source.extent_mm()
    if extent is None:
        raise ConfigError("extent_mm is needed: the recording names no shape to choose the grid around")
    return Grid(int(cfg.resolution), int(cfg.ndim), float(extent))


def acquisition_options(cfg: DictConfig, grid: Grid, shape: Shape | None, factory) -> dict[str, Any]:
    """The keyword arguments of a source's ``measure`` / ``record`` (:mod:`dipnet.preprocessing.sources`)
    from the job's config: the plan, slabs, object, seed, reach, loop solver, operators (of ``factory``)
    and symmetry."""
    n_slabs = cfg.n_slabs or grid.n
    reach = instantiate(cfg.reach) if cfg.get("reach") is not None else None
    return {"plan": instantiate(cfg.planner), "grid": grid, "n_slabs": n_slabs, "shape": shape, "seed": int(cfg.seed),
            "progress": bool(cfg.output.progress), "reach": reach, "solver": instantiate(cfg.solver),
            "make_operator": lambda directions: factory(grid, directions, n_slabs),
            "symmetry": OmegaConf.to_container(cfg.symmetry, resolve=True) if cfg.get("symmetry") else None}


def run(cfg: DictConfig, out: Path) -> JobResult:
    """Run one reconstruction job and write its outputs into ``out`` (every option checked first:
    :func:`dipnet.jobs.options.check_config`)."""
    cfg = upgrade_config(cfg)
    overrides, groups = hydra_overrides()
    check_config(cfg, overrides, groups)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_recording_not_overwritten(cfg, out)
    checkpoint_directory(cfg.output.get("checkpoint"), out)  # a file there: refused before any work
    earlier = output_files(out)
    torch.manual_seed(int(cfg.seed))
    configure_threads(cfg.get("threads"))
    check_memory(cfg)
    source = instantiate(cfg.source)
    shape = source.truth(lambda: instantiate(cfg.shape, ndim=int(cfg.ndim)), build=instantiate)
    grid = build_grid(cfg, shape, source)
    factory = instantiate(cfg.operator)
    options = acquisition_options(cfg, grid, shape, factory)
    if hasattr(options["solver"], "check_grid"):  # weights made for another grid: refused before any dip
        options["solver"].check_grid(grid, options["n_slabs"])
    calibration = instantiate(cfg.calibration) if cfg.get("calibration") else None
    if calibration is None:
        acquired = source.measure(**options)
        measurement, validation = acquired.measurement, acquired.validation
        measurement.metadata.update(mesh_frame(shape, measurement))  # a re-run from measurement.npz keeps the frame
        save_acquisition(out, acquired.raw, acquired.planning)
        measurement.save(out / "measurement.npz")
    else:  # the raw scan only: nothing is read with the uncalibrated geometry
        recording = source.record(**options)
        save_acquisition(out, recording.raw if recording.new else None, None)

    t0 = time.perf_counter()
    solver = instantiate(cfg.solver)
    checkpoint = attach_checkpoint(solver, cfg.output.get("checkpoint"), out,
                                   int(cfg.output.get("checkpoint_every", 25)))
    with checkpoint_directory_lock(None if checkpoint is None else checkpoint.directory):
        if calibration is not None:  # the rig geometry estimated jointly with the shape, before any check on it
            measurement, operator, recon = self_calibration_job(calibration, recording, grid, solver,
                                                                 options["n_slabs"], factory, out)
            validation = validate_measurement(measurement, grid)
        else:
            operator = options["make_operator"](measurement.directions)
            recon = solver.solve(measurement, operator)
    seconds = time.perf_counter() - t0
    recon.save(out / "reconstruction.npz")
    empty = warn_empty(recon)

    scores: dict[str, Any] = {"solver": recon.info.get("solver", type(solver).__name__),
                              "operator": recon.info.get("operator", backend_name(operator)),
                              "seconds": seconds, "n_dips": measurement.n_orientations,
                              "n_dips_measured": (measurement.metadata or {}).get("measured_orientations",
                                                                                  measurement.n_orientations),
                              "resolution": grid.n, "ndim": grid.ndim, "threshold": float(recon.threshold),
                              "empty": empty, **prior_weight_metrics(recon.info),
                              **surface_refit_metrics(recon.info),
                              **run_provenance()}
    stages = planned_stages(cfg.output, truth=shape is not None)
    stage = OutputStages(bool(cfg.output.progress), stages)
    stage("consistency")
    scores.update(consistency.check_consistency(measurement, operator, recon).metrics())  # warns of unmeasured bands
    if "resolvability" in stages:
        stage("resolvability")
        scores.update(write_resolvability(measurement, grid, out, figure=cfg.output.figures))
    truth = level = None
    if shape is not None:
        stage("truth and metrics")
        truth = shape.occupancy(grid, supersample=int(cfg.output.truth_supersample)).numpy()
        scores.update(shape=shape.name, snr_db=cfg.get("snr_db"))
        level = metrics.reference_level(truth, grid, shape.volume)
        scores.update(metrics.evaluate(recon, truth, grid, truth_mesh=getattr(shape, "mesh", None),
                                       truth_volume=shape.volume, truth_level=level))
        scores.update(metrics.reference_check(truth, grid, shape.volume, level))
        scores.update(metrics.false_rates(recon.binary, truth > level))
    frame = frame_offset(mesh_frame(shape, measurement), grid, scores)
    scores.update(validation.metrics())
    if "uncertainty" in stages:
        stage("uncertainty")
        method = "linearised" if cfg.output.uncertainty is True else str(cfg.output.uncertainty)
        reference = None if truth is None else truth > level  # the inside / outside that IoU and false rates score
        scores.update(write_uncertainty(out, recon, measurement, operator, reference, bool(cfg.output.figures), method,
                                        solver, int(cfg.output.get("uncertainty_samples") or 4), int(cfg.seed),
                                        float(cfg.output.get("uncertainty_iterations") or 1.0)))
    stage("meshes and figures")
    write_outputs(cfg, out, measurement, operator, recon, truth, level, frame)
    write_json(out / "metrics.json", scores, indent=2)  # last: a job killed before it shows as unfinished
    if "report" in stages:
        from dipnet.experiments.report import write_run_report  # optional extra: plotly

        stage("report")
        write_run_report(out)
    stage.close()
    warn_earlier_outputs(out, earlier, cfg)
    log.info("done: %s (every metric: %s)", headline(scores), out / "metrics.json")
    return JobResult(measurement, recon, scores, out)


def warn_empty(recon: Reconstruction) -> bool:
    """Say once, as the solve ends, that ``recon`` is empty (no voxel reaches its threshold), and what follows from
    it: no mesh, Chamfer and Hausdorff that are a stand-in, no calibration of the uncertainty (the later stages say
    no more of it). Returns whether it is empty."""
    if recon.binary.any():
        return False
    peak = float(recon.occupancy.max()) if recon.occupancy.numel() else float("nan")
    message = (f"the reconstruction is empty: no voxel of its occupancy reaches its threshold {recon.threshold:.6g} "
               f"(the largest is {peak:.3g}), so no shape came out of the solve: no mesh is written, its Chamfer and "
               f"Hausdorff are {metrics.EMPTY_DISTANCE:.1f} by convention (one truth diagonal, a stand-in that "
               "compare.py counts as an empty run, not a distance), and its uncertainty is not judged against the "
               "truth; look at the solver's settings (prior weights, iterations, threshold) and its log above")
    log_and_warn(log, message, stacklevel=2)
    return True


#: The files a reconstruction job may write into its run directory (meshes: :data:`MESH_NAMES` x any format).
RUN_OUTPUTS = ("measurement.npz", "rawscan.jsonl", "planning.json", "reconstruction.npz", "metrics.json",
               "resolvability.npz", "resolvability.png", "uncertainty.png", "sinogram.png", "profiles.png",
               "slices.png", "history.json", "loss.png", "mesh.png", "report.html", "plotly.min.js",
               "self_calibration.json", "rig_calibration.yaml")
MESH_NAMES = ("truth", "reconstruction")
MESH_SUFFIXES = (".ply", ".stl", ".obj")


def output_files(out: Path, names: Collection[str] | None = None) -> dict[str, tuple[int, int]]:
    """The job output files (:data:`RUN_OUTPUTS`, the meshes; or the files called ``names``, e.g. those of
    ``scripts/compare.py``) already in ``out``: name -> ``(inode, mtime in ns)``."""
    found = {}
    for path in out.iterdir() if out.is_dir() else ():
        known = path.name in names if names is not None else (
            path.name in RUN_OUTPUTS or (path.stem in MESH_NAMES and path.suffix in MESH_SUFFIXES))
        if known:
            try:
                stat = path.stat()
            except OSError:
                continue
            found[path.name] = (stat.st_ino, stat.st_mtime_ns)
    return found


def recording_path(cfg: DictConfig) -> Path | None:
    """The recording a job reads (``source.reader.path``, resolved), ``None`` for a simulated source."""
    recording = OmegaConf.select(cfg, "source.reader.path", default=None)
    return Path(str(recording)).resolve() if isinstance(recording, str) and recording != "???" else None


def check_recording_not_overwritten(cfg: DictConfig, out: Path) -> None:
    """Refuse a job that reads its recording from the file its own output would replace, ``out/measurement.npz``:
    a re-binned or symmetry-expanded copy would take the place of the data read, and a later run would solve the copy
    as if it were the recording. (A raw scan read from ``out/rawscan.jsonl`` is not written again.)

    Raises:
        ConfigError: ``source.reader.path`` is ``out/measurement.npz``.
    """
    source = recording_path(cfg)
    if source is not None and (out / "measurement.npz").resolve() == source:
        raise ConfigError(f"source.reader.path={source} lies in this run's output folder {out}, where the run writes "
                          f"its own {source.name}: the recording would be replaced by this run's copy of it "
                          "(re-binned to this grid's slabs, symmetry images added); give the run another "
                          "hydra.run.dir, or copy the recording elsewhere first")


def warn_earlier_outputs(out: Path, earlier: dict[str, tuple[int, int]], cfg: DictConfig) -> list[str]:
    """Warn about the output files an earlier job left in ``out`` that this job did not write again (``earlier``:
    :func:`output_files` before it ran): a mesh format or figure no longer asked for, a truth a recording does not
    have, a reconstruction too empty to mesh. They lie beside this job's results as if they were its own. The
    job's own input (a recording in ``out``) is not named. Returns their names."""
    source = recording_path(cfg)
    stale = [name for name in not_rewritten(out, earlier) if (out / name).resolve() != source]
    if stale:
        message = (f"{out} holds {len(stale)} file(s) of an earlier run that this run did not write: "
                   f"{', '.join(stale)}; they are not this run's results: delete them, or give each run its own "
                   "hydra.run.dir")
        log_and_warn(log, message, stacklevel=2)
    return stale


def not_rewritten(out: Path, earlier: dict[str, tuple[int, int]]) -> list[str]:
    """The names among ``earlier`` (:func:`output_files` of ``out`` before a job or a comparison wrote into it)
    whose files are still the same (inode and modification time), sorted: left there by an earlier one."""
    now = output_files(out, earlier)
    return sorted(name for name, mark in earlier.items() if now.get(name) == mark)


def save_acquisition(out: Path, raw: RawScan | None, planning: dict | None) -> None:
    """Save what the run made while dipping: its raw scan (``rawscan.jsonl``) and a plan's report
    (``planning.json``)."""
    if raw is not None:
        raw.save(out / "rawscan.jsonl")
    if planning is not None:
        write_json(out / "planning.json", planning, indent=2)


def run_provenance() -> dict[str, Any]:
    """``{"overrides": the job's command-line overrides, "solver_config": the solver config chosen}`` in a Hydra run
    (``scripts/reconstruct.py``, a sweep job), the overrides as typed (``n_slabs=${resolution}`` unresolved, as in
    ``.hydra/overrides.yaml``), else ``{}``: whose metrics ``metrics.json`` holds, and by which recipe (``solver``
    names the solver's class: ``voxel`` for ``solver=voxel_learned``). A later run into the same folder rewrites
    ``.hydra/overrides.yaml`` as it starts and ``metrics.json`` only when it finishes
    (:func:`dipnet.experiments.collect.earlier_metrics`). Outside Hydra (the compose API of ``tune.py``, which
    writes the trial's ``.hydra/`` itself) there is no record to compare with."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    return {"overrides": [str(o) for o in OmegaConf.to_container(HydraConfig.get().overrides.task, resolve=False)],
            "solver_config": HydraConfig.get().runtime.choices.get("solver")}


#: The keys of a mesh file's frame in ``metrics.json`` and in the metadata of the job's ``measurement.npz``
#: (``frame_axes``: in 2D, the file's axes that the 2D ``x, y`` are, e.g. ``"zx"`` for a silhouette along y).
FRAME_KEYS = ("frame_offset_mm", "frame_scale", "frame_axes")
#: The 2D planes a silhouette of a mesh file lies in (``shape.axis`` x, y, z).
FRAME_AXES_2D = ("yz", "zx", "xy")


def mesh_frame(shape: Shape | None, measurement: DipMeasurement | None = None) -> dict[str, Any]:
    """The frame of the user's mesh file, as :data:`FRAME_KEYS` (only those that are not the identity):
    ``frame_offset_mm`` (3,) mm, the shift from the grid frame, and ``frame_scale``, the mm per unit of the file
    (``shape.radius``, ``shape.scale``). From the shape (``shape=mesh``), else from the metadata of a measurement
    a mesh job saved (a run of ``source=recorded`` on its ``measurement.npz``); ``{}`` for neither."""
    offset = getattr(shape, "frame_offset", None)
    if offset is None:
        return saved_frame(measurement.metadata if measurement is not None else {})
    frame: dict[str, Any] = {}
    if np.any(offset != 0):
        frame["frame_offset_mm"] = [float(v) for v in offset]
    if float(getattr(shape, "frame_scale", 1.0)) != 1.0:
        frame["frame_scale"] = float(shape.frame_scale)
    axes = getattr(shape, "frame_axes", None)
    if axes in FRAME_AXES_2D and (frame or axes != "xy"):  # a silhouette: the file's axes its x, y are
        frame["frame_axes"] = axes
    return frame


def saved_frame(metadata: dict[str, Any]) -> dict[str, Any]:
    """The :data:`FRAME_KEYS` a measurement's ``metadata`` holds, those that are well formed (an offset of three
    finite mm, a finite positive scale); another value (a hand-edited file) is left out with a warning."""
    frame: dict[str, Any] = {}
    axes = metadata.get("frame_axes")
    size = 2 if axes is not None else 3
    if axes is not None and axes not in FRAME_AXES_2D:
        log.warning("the measurement's frame_axes=%r is not one of %s: its frame is left out", axes, FRAME_AXES_2D)
        return frame
    for key, size in (("frame_offset_mm", size), ("frame_scale", None)):
        if metadata.get(key) is None:
            continue
        try:
            value = np.asarray(metadata[key], dtype=np.float64)
        except (TypeError, ValueError):
            value = np.full(1, np.nan)
        if value.shape == ((size,) if size else ()) and np.isfinite(value).all() and (size or value > 0):
            frame[key] = value.tolist()
        else:
            log.warning("the measurement's %s=%r is not %s: left out, so the meshes of this run are not placed by it",
                        key, metadata[key], f"{'three' if size == 3 else 'two'} finite mm" if size
                        else "a finite positive number")
    if frame and axes is not None:
        frame["frame_axes"] = axes
    return frame


def frame_offset(frame: dict[str, Any], grid: Grid, scores: dict[str, Any]) -> np.ndarray | None:
    """The shift (3,) mm from the grid frame to the frame of the user's mesh file (``None``: no
    shift), from ``frame`` (:func:`mesh_frame`), stated with the scale in ``scores`` and the log (the
    mesh files are written in the file's frame, in mm; volumes and figures stay centred). A vertex ``v``
    (mm) of a mesh file is ``v / frame_scale`` in the file's own units. In 2D (a silhouette of a mesh file) the
    frame is stated and logged, with the file's axes the 2D ``x, y`` are (``frame_axes``), and ``None`` returned:
    no mesh file is written."""
    if not frame or len(frame.get("frame_offset_mm", [0.0] * grid.ndim)) != grid.ndim:
        return None
    scores.update(frame)
    if grid.ndim == 2:  # no mesh file: the frame is stated for reconstruction.npz and the figures
        axes = frame.get("frame_axes", "xy")
        log.info("the 2D results (reconstruction.npz, slices.png) are centred; their x, y are the %s, %s axes of the "
                 "shape's file: add frame_offset_mm %s and divide by frame_scale %s for the file's coordinates",
                 axes[0], axes[1], [round(float(v), 4) for v in frame.get("frame_offset_mm", [0.0, 0.0])],
                 frame.get("frame_scale", 1.0))
        return None
    if "frame_scale" in frame:
        log.info("the mesh was scaled by %.6g (frame_scale, mm per unit of its file): divide the mesh files' "
                 "vertices by it for the file's units", frame["frame_scale"])
    if "frame_offset_mm" not in frame:
        return None
    offset = np.asarray(frame["frame_offset_mm"], dtype=np.float64)
    log.info("mesh files are in the frame of the shape's file: grid frame + %s mm (frame_offset_mm); "
             "volumes and figures are centred", [round(float(v), 4) for v in offset])
    return offset


def write_outputs(cfg, out: Path, measurement, operator, recon: Reconstruction, truth, level: float | None = None,
                  offset: np.ndarray | None = None) -> None:
    """Meshes (3D; moved by ``offset`` (3,) mm into the frame of the user's mesh file) and
    PNG figures of one job (``level``: the truth occupancy counted as inside in the slices). The
    reconstruction's mesh is its surface refitted to the dips when the solver refitted one
    (:attr:`Reconstruction.mesh`: ``solver.surface_refit``), else from its finer sampling when the solver made one
    (:attr:`Reconstruction.fine`: ``solver=implicit solver.output_upsample=2``), as the log says; its
    volume, metrics and figures stay on the data grid."""
    grid = recon.grid
    meshes = []
    if grid.ndim == 3:
        if truth is not None:
            meshes.append((volume_to_mesh(truth, grid, 0.5), "truth"))
        surface = recon.fine if recon.fine is not None and recon.fine.grid.ndim == 3 else recon
        if recon.mesh is not None:
            log.info("the reconstruction's mesh is its surface refitted to the dips (solver.surface_refit); "
                     "reconstruction.npz and the figures hold the voxel result it started from")
            meshes.append((recon.mesh, "reconstruction"))
        else:
            if surface is not recon:
                log.info("the reconstruction's mesh is its field sampled at %d^3 (the solver's finer sampling, "
                         "solver.output_upsample); reconstruction.npz, the metrics and the figures are on the %d^3 "
                         "grid", surface.grid.n, grid.n)
            meshes.append((volume_to_mesh(surface.occupancy.detach().cpu().numpy(), surface.grid,
                                          surface.threshold), "reconstruction"))
        for mesh, name in meshes:
            if len(mesh.faces):
                placed = mesh if offset is None else mesh.copy().apply_translation(offset)
                for fmt in cfg.output.mesh_formats:
                    export.save_mesh(placed, out / f"{name}.{fmt}")
            elif name == "reconstruction" and not recon.binary.any():  # warned once as the solve ended
                log.info("the reconstruction is empty, so %s was not written",
                         ", ".join(f"{name}.{fmt}" for fmt in cfg.output.mesh_formats))
            else:
                why = ("its surface is empty (no point of the solver's finer sampling reaches the threshold "
                       f"{recon.threshold:.6g})" if name == "reconstruction" else
                       "the true shape has no surface on this grid (no voxel more than half inside)")
                log.warning("%s, so %s was not written", why,
                            ", ".join(f"{name}.{fmt}" for fmt in cfg.output.mesh_formats))
    if not cfg.output.figures:
        return
    with torch.no_grad():
        predicted = operator(torch.as_tensor(recon.binary, dtype=torch.float64))
    plots.plot_sinogram(measured_profiles(measurement, operator).numpy(), out / "sinogram.png",
                        slab_edges=operator.slab_edges().numpy(), volume_unit_2d=grid.ndim == 2)
    plots.plot_profiles(measured_profiles(measurement, operator).numpy(), predicted.numpy(), out / "profiles.png",
                        slab_edges=operator.slab_edges().numpy(), volume_unit_2d=grid.ndim == 2)
    if truth is not None:
        plots.plot_slices(truth, recon.binary.astype(float), out / "slices.png", extent_mm=grid.extent,
                          truth_level=0.5 if level is None else level)
    if recon.history:
        write_json(out / "history.json", recon.history)
        plots.plot_history(recon.history, out / "loss.png")
    if meshes:
        plots.plot_mesh([m for m, _ in meshes], out / "mesh.png", titles=[t for _, t in meshes])


def config_summary(cfg: DictConfig) -> str:
    """The resolved config as YAML (for logs and headers)."""
    return OmegaConf.to_yaml(cfg, resolve=True)
