"""Up-front checks of a reconstruction config: every option is valid, and read, before any work.

:func:`check_config` runs at the start of :func:`dipnet.jobs.pipeline.run`, so a bad option ends in
one ``error: ...`` line (exit 2, see :mod:`dipnet.jobs.cli`) before anything is simulated, solved or
written, and a sweep job with a bad option fails instead of counting as finished. It refuses:

* values out of range (``resolution=abc``, ``seed=-1``, ``snr_db=abc``, ``source.simulator.smooth=maybe``, an unknown
  mesh format, ``output.report=true`` without the ``report`` extra, ``symmetry={n_fold: 2.5}``, and the counts and sizes
  of a ``_target_`` node by its target, :data:`TARGET_COUNTS`, e.g. ``solver.hidden_width=0``), naming the option and
  the allowed values;
* options no code reads: a key of a ``_target_`` node that its target does not take (following
  ``**options`` through :func:`~dipnet.core.keywords.forwards_to`), e.g. ``+operator.bogus_option=1``, and a key added
  with ``+`` anywhere else (``+n_dip=40`` for ``n_dips=40``);
* options the chosen source, planner or ``ndim`` ignores (:data:`IGNORED`), e.g. ``n_dips`` or
  ``planner=adaptive`` with ``source=recorded``, and ``reach`` with ``ndim=2``.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

from omegaconf import DictConfig, ListConfig, OmegaConf

from dipnet.calibration.model import CalibrationError
from dipnet.calibration.self_calibration import SelfCalibrator, check_section_change
from dipnet.core.keywords import accepted_keywords
from dipnet.operators import ALIASES, fourier
from dipnet.planning.plans import AdaptivePlan
from dipnet.preprocessing.sources import RecordedSource
from dipnet.preprocessing.symmetry import MAX_MERGE_DEG
from dipnet.shapes.procedural import generated_shape
from dipnet.simulator.physics import check_snr_db
from dipnet.simulator.source import SimulatedSource
from dipnet.solvers.implicit import ImplicitSolver
from dipnet.solvers.optimize import OptimisationSolver
from dipnet.solvers.priors import prior_weight

#: Hydra's own keys of a ``_target_`` node (not arguments of the target).
HYDRA_KEYS = frozenset({"_target_", "_partial_", "_args_", "_recursive_", "_convert_"})
#: A key a config node does not set (``OmegaConf.select``'s default).
_UNSET = object()
#: Mesh formats of ``output.mesh_formats`` (:func:`dipnet.outputs.export.save_mesh`).
MESH_FORMATS = ("ply", "stl", "obj")
#: The reader's options for a raw recording (:func:`~dipnet.preprocessing.recorded.read_raw_recording`), which a
#: ``.npz`` measurement does not read (:func:`~dipnet.preprocessing.sources.read_recorded` re-bins its profiles).
RAW_READER_OPTIONS = ("truncated", "calibration", "smooth", "geometry", "cross_section_mm2", "fixture", "t_start",
                      "centre", "tail_fraction", "tail_tol", "interpolate")  # (symmetry: moved to the top level)


def reads_a_measurement_file(cfg: DictConfig) -> bool:
    """Whether ``cfg`` reads a recorded ``.npz`` measurement (``source=recorded``, ``source.reader.path=*.npz``)."""
    if not instantiates(cfg, "source", RecordedSource):
        return False
    path = OmegaConf.select(cfg, "source.reader.path", default=None, throw_on_missing=False)
    return isinstance(path, str) and path.lower().endswith(".npz")


#: Options (or config groups) a choice does not read: ``(the choice as typed, whether a config makes it,
#: ignored options (an option or a node, with every key below it), why)``.
IGNORED: tuple[tuple[str, Callable[[DictConfig], bool], tuple[str, ...], str], ...] = (
    ("source=recorded", lambda cfg: instantiates(cfg, "source", RecordedSource),
     ("n_dips", "orientations", "snr_db", "shape", "reach", "output.truth_supersample"),
     "the recording fixes the dips, their directions, their noise and the object, and holds no ground truth to "
     "sample"),
    ("an .npz source.reader.path", reads_a_measurement_file,
     tuple(f"source.reader.{key}" for key in RAW_READER_OPTIONS),
     "a measurement file holds slab profiles already made from readings: its rig geometry, calibration, tank section, "
     "smoothing and dropped dips were applied when it was written; read the raw scan (.jsonl, .csv) to change them"),
    ("planner=adaptive", lambda cfg: instantiates(cfg, "planner", AdaptivePlan), ("n_dips", "orientations"),
     "the planner chooses the dips: set planner.budget"),
    ("ndim=2", lambda cfg: cfg.get("ndim") == 2, ("reach",),
     "a reach is the 3D rig's tilt and spin range; 2D dips are angles in the plane, set by n_dips and orientations"),
    ("ndim=2", lambda cfg: cfg.get("ndim") == 2, ("output.mesh_formats",),
     "a 2D job writes no mesh: its shape is in reconstruction.npz and slices.png"),
    ("ndim=3", lambda cfg: cfg.get("ndim") == 3, ("shape.axis",),
     "the axis a mesh is projected along makes its 2D silhouette, for ndim=2"),
    ("source=simulated", lambda cfg: instantiates(cfg, "source", SimulatedSource), ("source.simulator.sensor.seed",),
     "the job's seed sets the simulated noise: give seed=... instead"),
    ("extent_mm set", lambda cfg: cfg.get("extent_mm") is not None, ("fill",),
     "fill chooses the grid's side around the object only when extent_mm is null; the extent_mm given is the side"),
    ("solver.method=cholesky", lambda cfg: OmegaConf.select(cfg, "solver.method") == "cholesky",
     ("solver.iter_lim",), "iter_lim bounds the iterative methods (lsmr, lsqr; auto on large problems), "
     "the Cholesky factorisation is direct"),
    ("output.uncertainty other than samples", lambda cfg: OmegaConf.select(cfg, "output.uncertainty") != "samples",
     ("output.uncertainty_samples", "output.uncertainty_iterations"),
     "they size the ensemble of output.uncertainty=samples; true / linearised is one Gaussian posterior, false none: "
     "set output.uncertainty=samples for an ensemble"),
    ("output.checkpoint=null", lambda cfg: OmegaConf.select(cfg, "output.checkpoint") in (None, False),
     ("output.checkpoint_every",), "it sets how often output.checkpoint saves a solve, and no checkpoint is kept: "
     "set output.checkpoint=true (or a directory) to keep one"),
)
#: The most sub-voxel samples per axis of the truth occupancy (``output.truth_supersample``): a sampled shape tests
#: their cube per voxel (16: 4096), and finer sampling changes only the partial volume of the boundary voxels.
MAX_TRUTH_SUPERSAMPLE = 16
#: Keys of the top-level ``symmetry`` (:func:`dipnet.preprocessing.symmetry.apply_symmetry`).
SYMMETRY_KEYS = ("n_fold", "mirror", "mirror_azimuth_deg", "tol_deg")


class Count(NamedTuple):
    """An integer option: its lowest value, what it counts, and whether null (the target's choice) is allowed."""

    low: int
    meaning: str
    nullable: bool = False


#: Integer options of a ``_target_`` node, by its target (a class also covers its subclasses), wherever the
#: node is (``solver``, ``solver.warm_start``, ``calibration.gain_solver``, ...), by their key below the node;
#: a key the node does not set keeps the target's default.
TARGET_COUNTS: tuple[tuple[Any, dict[str, Count]], ...] = (
    (OptimisationSolver, {"iterations": Count(1, "optimisation steps"),
                          "window": Count(1, "steps of the plateau test")}),
    (ImplicitSolver, {"hidden_width": Count(1, "neurons per hidden layer"), "hidden_layers": Count(0, "hidden layers"),
                      "output_upsample": Count(1, "fine samples per voxel and axis"),
                      "warm_iterations": Count(0, "warm-start steps"), "encoding.levels": Count(1, "grid levels"),
                      "encoding.features": Count(1, "features per level"),
                      "encoding.base_resolution": Count(2, "coarsest cells per axis"),
                      "encoding.max_resolution": Count(2, "finest cells per axis; null: the grid's", nullable=True),
                      "encoding.n_features": Count(1, "random Fourier features"),
                      "encoding.n_frequencies": Count(1, "frequencies per axis")}),
    (SelfCalibrator, {"iterations": Count(1, "rounds of the joint shape + cross-section step")}),
    (generated_shape, {"seed": Count(0, "which solid"), "mesh_resolution": Count(16, "marching-cubes cells per axis")}),
)


class ConfigError(ValueError):
    """A configuration value is out of range, inconsistent, or read by no code."""


def unknown_option(name: str, known: Sequence[str], why: str = "no code reads it") -> ConfigError:
    """The error for option ``name`` (dotted), suggesting the closest of ``known`` (leaf names)."""
    leaf = name.rsplit(".", 1)[-1]
    close = difflib.get_close_matches(leaf, list(known), n=1)
    hint = f"; did you mean {name[:len(name) - len(leaf)]}{close[0]}?" if close else ""
    return ConfigError(f"unknown option {name}: {why}{hint}")


def _target_nodes(node: Any, path: str = "") -> Iterator[tuple[str, DictConfig]]:
    """``(dotted path, node)`` of every ``_target_`` node under ``node`` (Hydra's own settings left out)."""
    if isinstance(node, DictConfig):
        if "_target_" in node:
            yield path, node
        items = ((str(k), node._get_node(k)) for k in node.keys() if not (path == "" and k == "hydra"))
    elif isinstance(node, ListConfig):
        items = ((str(i), node._get_node(i)) for i in range(len(node)))
    else:
        return
    for key, child in items:
        yield from _target_nodes(child, f"{path}.{key}" if path else key)


def instantiates(cfg: DictConfig, group: str, cls: type) -> bool:
    """Whether config group ``group`` of ``cfg`` instantiates ``cls`` (or a subclass): its ``_target_``."""
    from hydra._internal.utils import _locate

    target = OmegaConf.select(cfg, f"{group}._target_", default=None)
    located = _locate(str(target)) if target is not None else None
    return isinstance(located, type) and issubclass(located, cls)


def check_targets(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a key of a ``_target_`` node that its target does not take."""
    for path, node in _target_nodes(cfg):
        target = _located(node)
        accepted = accepted_keywords(target)
        if accepted is None:
            continue
        for key in node.keys():
            if key not in HYDRA_KEYS and key not in accepted:
                name = getattr(target, "__name__", str(target))
                raise unknown_option(f"{path}.{key}" if path else str(key), sorted(accepted),
                                     f"{name} takes {', '.join(sorted(accepted))}")


def _inside_target(cfg: DictConfig, key: str) -> bool:
    """Whether dotted ``key`` lies below a ``_target_`` node of ``cfg`` (which :func:`check_targets` checks)."""
    parts = key.split(".")
    for i in range(1, len(parts)):
        node = OmegaConf.select(cfg, ".".join(parts[:i]), throw_on_resolution_failure=False)
        if isinstance(node, DictConfig) and "_target_" in node:
            return True
    return False


def check_overrides(cfg: DictConfig, overrides: Sequence[str], groups: Sequence[str] = ()) -> None:
    """Raise :class:`ConfigError` for a command-line override no code reads: a key added with ``+``
    outside a ``_target_`` node, an option the chosen source, planner or ``ndim`` ignores (:data:`IGNORED`),
    or ``planner=adaptive`` with ``source=recorded``.

    Args:
        overrides: the job's overrides as typed (``hydra.overrides.task``).
        groups: the config groups (``hydra.runtime.choices``): ``+group=...`` is not a new key.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(list(overrides))
    for o in parsed:
        key = o.key_or_group
        if o.is_add() and key not in groups and not key.startswith("hydra.") and not _inside_target(cfg, key):
            parent = OmegaConf.select(cfg, key.rsplit(".", 1)[0]) if "." in key else cfg
            known = [str(k) for k in parent.keys() if str(k) != key.rsplit(".", 1)[-1]] \
                if isinstance(parent, DictConfig) else []
            raise unknown_option(key, known)
    if instantiates(cfg, "source", RecordedSource) and instantiates(cfg, "planner", AdaptivePlan):
        raise ConfigError("planner=adaptive is ignored with source=recorded: the recording's dips are fixed; plan "
                          "a scan dip by dip on the rig (scripts/scan.py +planner=adaptive) or with simulated dips")
    typed = {o.key_or_group for o in parsed if not o.is_delete()}
    posterior = OmegaConf.select(cfg, "planner.planner.resolution", default=None)
    if "planner.planner.resolution" in typed and instantiates(cfg, "planner", AdaptivePlan) \
            and isinstance(posterior, int) and isinstance(cfg.get("resolution"), int) and posterior > cfg.resolution:
        raise ConfigError(f"planner.planner.resolution={posterior} is above the job's resolution={cfg.resolution}: "
                          "the planner's posterior grid is at most the reconstruction's (it would run at "
                          f"{cfg.resolution}, unsaid): give planner.planner.resolution <= {cfg.resolution}, or raise "
                          "resolution")
    for choice, chosen, ignored, why in IGNORED:
        if not chosen(cfg):
            continue
        for o in parsed:
            asks_nothing = o.is_delete() or (o.value_type is not None and o.value() == [])  # mesh_formats=[]
            if any(o.key_or_group == k or o.key_or_group.startswith(f"{k}.") for k in ignored) and not asks_nothing:
                raise ConfigError(f"option {o.key_or_group} is ignored with {choice} ({why}): remove it")


def _integer(cfg: DictConfig, key: str, low: int, high: float = math.inf, *, nullable: bool = False,
             meaning: str = "") -> None:
    value = OmegaConf.select(cfg, key)
    if value is None and nullable:
        return
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value < high:
        kind = "a positive integer" if low == 1 else f"an integer >= {low}"
        upper = "" if high == math.inf else f" and below {high:.0f}"
        raise ConfigError(f"{key} must be {kind}{upper}{' or null' if nullable else ''}{meaning}, got {value!r}")


def _number(cfg: DictConfig, key: str, low: float = -math.inf, *, positive: bool = False, nullable: bool = False,
            meaning: str = "") -> None:
    """Raise :class:`ConfigError` unless option ``key`` is a finite number ``>= low`` (``> 0`` with ``positive``),
    or null with ``nullable``."""
    value = OmegaConf.select(cfg, key)
    if value is None and nullable:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value < low or (positive and not value > 0):
        kind = "a positive number" if positive else "a finite number" if low == -math.inf else f"a number >= {low:g}"
        raise ConfigError(f"{key} must be {kind}{' or null' if nullable else ''}{meaning}, got {value!r}")


def _located(node: DictConfig) -> Any:
    """The object a ``_target_`` node names."""
    from hydra._internal.utils import _locate

    return _locate(str(node._get_node("_target_")._value()))


def _is_target(located: Any, target: Any) -> bool:
    """Whether a located ``_target_`` is ``target`` (or a subclass of the class ``target``)."""
    return located is target or (isinstance(located, type) and isinstance(target, type) and issubclass(located, target))


def check_target_counts(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for an option of :data:`TARGET_COUNTS` below its lowest value or not an
    integer (e.g. ``solver.hidden_width=0``, ``calibration.iterations=0``, ``shape.mesh_resolution=2``)."""
    for path, node in _target_nodes(cfg):
        located = _located(node)
        for target, counts in TARGET_COUNTS:
            if not _is_target(located, target):
                continue
            for key, count in counts.items():
                if OmegaConf.select(node, key, default=_UNSET) is not _UNSET:
                    _integer(cfg, f"{path}.{key}", count.low, nullable=count.nullable, meaning=f" ({count.meaning})")


def check_self_calibration(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a ``calibration=self`` option out of range (its counts:
    :func:`check_target_counts`)."""
    if not instantiates(cfg, "calibration", SelfCalibrator):
        return
    if cfg.get("ndim") == 2:
        raise ConfigError("calibration=self fits the 3D rig's geometry (pivot, tilt axis, spin) from the dips' tilts "
                          "and spins; 2D dips are angles in the plane, with no rig angles: set ndim=3, or drop "
                          "calibration=self")
    _number(cfg, "calibration.dip_offset_sigma_mm", positive=True, nullable=True,
            meaning=" (mm, the prior of each dip's height offset; null: no offsets)")
    _number(cfg, "calibration.max_section_change", positive=True, nullable=True,
            meaning=" (relative change of the cross-section)")
    try:
        check_section_change(OmegaConf.select(cfg, "calibration.max_section_change"))
    except CalibrationError as exc:
        raise ConfigError(f"calibration.{exc}") from None
    for key in ("section_min_resolution", "section_min_dips"):
        if OmegaConf.select(cfg, f"calibration.{key}", default=_UNSET) is not _UNSET:
            _integer(cfg, f"calibration.{key}", 0, meaning=" (0: trust the section at any grid and number of dips)")


def check_symmetry(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a ``symmetry`` that is not null or ``{n_fold, mirror, mirror_azimuth_deg,
    tol_deg}`` with a positive integer, a boolean and numbers
    (:func:`~dipnet.preprocessing.symmetry.symmetry_group`)."""
    spec = cfg.get("symmetry")
    if spec is None:
        return
    if not isinstance(spec, DictConfig):
        raise ConfigError(f"symmetry must be null or {{{', '.join(SYMMETRY_KEYS)}}}, e.g. "
                          f"'{{n_fold: 3, mirror: true}}', got {spec!r}")
    for key in spec.keys():
        if key not in SYMMETRY_KEYS:
            raise unknown_option(f"symmetry.{key}", SYMMETRY_KEYS, f"symmetry takes {', '.join(SYMMETRY_KEYS)}")
    if cfg.get("ndim") == 2:
        raise ConfigError(f"symmetry={OmegaConf.to_container(spec)} copies 3D dips to their images about the vertical "
                          "axis z, which a 2D object does not have: set symmetry=null with ndim=2; "
                          "a 2D object's mirror "
                          "line or rotation is a solver prior (solver=voxel solver.priors.symmetry.weight=1 "
                          "'solver.priors.symmetry.plane_normal=[1,0]', or solver=implicit "
                          "'solver.symmetry={plane_normal: [1, 0]}')")
    if "n_fold" in spec:
        _integer(cfg, "symmetry.n_fold", 1, meaning=" (rotations about z)")
    if "mirror" in spec and not isinstance(spec.mirror, bool):
        raise ConfigError(f"symmetry.mirror must be true or false, got {spec.mirror!r}")
    if "mirror_azimuth_deg" in spec:
        _number(cfg, "symmetry.mirror_azimuth_deg", meaning=" (deg)")
    if "tol_deg" in spec:
        _number(cfg, "symmetry.tol_deg", 0, meaning=" (deg)")
        if spec.tol_deg > MAX_MERGE_DEG:
            raise ConfigError(f"symmetry.tol_deg must be at most {MAX_MERGE_DEG:g} (deg), got {spec.tol_deg!r}: "
                              "directions further apart have different profiles, and merging them would average "
                              "distinct dips into one")
    _check_symmetry_declares_something(spec)


def _check_symmetry_declares_something(spec: DictConfig) -> None:
    """Raise :class:`ConfigError` for a ``symmetry`` whose group is the identity (``{}``, ``{n_fold: 1}``: no dip
    gains an image, the job ran as without it) or whose ``mirror_azimuth_deg`` (deg) places no mirror (``mirror``
    not true): both ran, exit 0, as if no symmetry was declared."""
    mirror = bool(spec.get("mirror", False))
    if "mirror_azimuth_deg" in spec and not mirror:
        raise ConfigError(f"option symmetry.mirror_azimuth_deg is ignored with symmetry.mirror=false (it places the "
                          f"mirror plane, deg): add mirror: true (symmetry={{n_fold: "
                          f"{spec.get('n_fold', 1)}, mirror: true, mirror_azimuth_deg: {spec.mirror_azimuth_deg}}}), "
                          "or remove it")
    if int(spec.get("n_fold", 1)) == 1 and not mirror:
        raise ConfigError(f"symmetry={OmegaConf.to_container(spec)} declares no symmetry (n_fold 1 without a "
                          "mirror: the identity), so no dip gains an image: give n_fold >= 2 or mirror: true "
                          "(e.g. symmetry={n_fold: 3, mirror: true}), or symmetry=null")


def check_grid_options(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a bad ``ndim``, ``resolution``, ``n_dips``, ``n_slabs``,
    ``fill`` or ``extent_mm``."""
    if cfg.get("ndim") not in (2, 3):
        raise ConfigError(f"ndim must be 2 or 3, got {cfg.get('ndim')!r}")
    _integer(cfg, "resolution", 4, meaning=" (voxels per axis)")
    _integer(cfg, "n_dips", 1)
    _integer(cfg, "n_slabs", 3, nullable=True,
             meaning=" (slabs per profile: the noise the consistency check allows is estimated from 3 neighbours)")
    fill = cfg.get("fill")
    if isinstance(fill, bool) or not isinstance(fill, (int, float)) or not 0 < fill <= 1:
        raise ConfigError(f"fill must be a number in (0, 1], got {fill!r}")
    extent = cfg.get("extent_mm")
    if extent is not None and (isinstance(extent, bool) or not isinstance(extent, (int, float))
                               or not 0 < extent < math.inf):
        raise ConfigError(f"extent_mm must be a positive number (mm) or null, got {extent!r}")


def check_thresholds(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a numeric ``threshold`` of the solver (or of a solver it nests, e.g.
    ``solver.warm_start``) outside the occupancy levels (0, 1): its binary shape would be empty or full.
    A named rule (``otsu``, ``volume``) is the solver's to check."""
    solver = cfg.get("solver")
    for path, node in _target_nodes(solver, "solver") if isinstance(solver, DictConfig) else ():
        level = node.get("threshold")
        if isinstance(level, bool) or (isinstance(level, (int, float)) and not 0 < level < 1):
            raise ConfigError(f"{path}.threshold must be an occupancy level in (0, 1) or the solver's rule "
                              f"(otsu, volume), got {level!r}")


def check_prior_weights(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a numeric prior weight of the solver (or of a solver it nests) that is negative,
    NaN or infinite (:func:`~dipnet.solvers.priors.prior_weight`), before any work: ``tune.py --param
    solver.priors.tv.weight=-1:1:linear`` would fail every trial that draws a negative weight."""
    solver = cfg.get("solver")
    for path, node in _target_nodes(solver, "solver") if isinstance(solver, DictConfig) else ():
        priors = node.get("priors")
        for name, options in (priors.items() if isinstance(priors, DictConfig) else ()):
            weight = options.get("weight") if isinstance(options, DictConfig) else options
            if isinstance(weight, (int, float)) and not isinstance(weight, bool):
                try:
                    prior_weight(str(name), weight)
                except ValueError as exc:
                    raise ConfigError(f"{path}.priors.{name}.weight: {exc}") from None


def check_operator(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a bad option of ``operator=fourier``
    (:func:`dipnet.operators.fourier.check_options`) before any work: the operator is built only once the dips are
    measured, and ``operator.upsampfac=nan`` crashed the process there (segmentation fault in finufft)."""
    node = cfg.get("operator")
    if not isinstance(node, DictConfig) or ALIASES.get(node.get("backend"), node.get("backend")) != "fourier":
        return
    keys = [k for k in accepted_keywords(fourier.check_options) or () if k in node]
    try:
        fourier.check_options(**{k: node.get(k) for k in keys})
    except ValueError as exc:
        raise ConfigError(f"operator.{exc}") from None


def check_values(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for an option of :file:`conf/config.yaml` out of its range."""
    check_grid_options(cfg)
    check_thresholds(cfg)
    check_prior_weights(cfg)
    check_target_counts(cfg)
    check_operator(cfg)
    check_self_calibration(cfg)
    check_symmetry(cfg)
    _integer(cfg, "seed", 0, 2.0 ** 32)
    _integer(cfg, "threads", 1, nullable=True)
    try:
        check_snr_db(cfg.get("snr_db"))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    for key in ("source.simulator.smooth", "source.reader.smooth"):
        smooth = OmegaConf.select(cfg, key, default=False)
        if not isinstance(smooth, bool):
            raise ConfigError(f"{key} must be true or false, got {smooth!r}")
    for key in ("output.figures", "output.progress", "output.report", "output.resolvability", "operator.single",
                "shape.fill_sealed_voids"):  # a string is true: figures=no drew them, single=no ran in complex64
        value = OmegaConf.select(cfg, key, default=False)
        if not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
    formats = cfg.output.get("mesh_formats")
    if not isinstance(formats, ListConfig) or any(f not in MESH_FORMATS for f in formats):
        raise ConfigError(f"output.mesh_formats must be a list of {', '.join(MESH_FORMATS)}, got "
                          f"{OmegaConf.to_container(formats) if isinstance(formats, ListConfig) else formats!r}")
    _integer(cfg, "output.truth_supersample", 1, MAX_TRUTH_SUPERSAMPLE + 1,
             meaning=" (sub-voxel samples per axis of the truth's partial volume: a sampled shape tests their cube "
                     "in every voxel)")
    _integer(cfg, "output.checkpoint_every", 1)
    _integer(cfg, "output.uncertainty_samples", 2, nullable=True)
    method = cfg.output.get("uncertainty")
    if method not in (True, False, None, "linearised", "samples"):
        raise ConfigError(f"output.uncertainty must be true, false, linearised or samples, got {method!r}")
    scale = cfg.output.get("uncertainty_iterations")
    if scale is not None and (isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 < scale <= 1):
        raise ConfigError(f"output.uncertainty_iterations must be a number in (0, 1], got {scale!r}")
    if cfg.output.get("report"):
        from dipnet.experiments.report import require_plotly

        try:
            require_plotly()
        except ImportError as exc:
            raise ConfigError(f"output.report=true: {exc}") from None


def check_config(cfg: DictConfig, overrides: Sequence[str] = (), groups: Sequence[str] = ()) -> None:
    """Every check of this module (see the module docstring); raises :class:`ConfigError`."""
    check_values(cfg)
    check_targets(cfg)
    check_overrides(cfg, overrides, groups)


def hydra_overrides() -> tuple[list[str], list[str]]:
    """``(the job's command-line overrides, its config groups)`` in a Hydra run, else ``([], [])``."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return [], []
    hydra_cfg = HydraConfig.get()
    return list(hydra_cfg.overrides.task), [str(g) for g in hydra_cfg.runtime.choices]
