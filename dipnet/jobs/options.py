"""Up-front checks of a reconstruction config: every option is valid, and read, before any work.

:func:`check_config` runs at the start of :func:`dipnet.jobs.pipeline.run`, so a bad option ends in
one ``error: ...`` line (exit 2, see :mod:`dipnet.jobs.cli`) before anything is simulated, solved or
written, and a sweep job with a bad option fails instead of counting as finished. It refuses:

* values out of range (``resolution=abc``, ``seed=-1``, ``snr_db=abc``, ``source.simulator.smooth=maybe``, an unknown mesh format,
  ``output.report=true`` without the ``report`` extra), naming the option and the allowed values;
* options no code reads: a key of a ``_target_`` node that its target does not take (following
  ``**options`` through :func:`~dipnet.core.keywords.forwards_to`), e.g. ``+operator.bogus_option=1``, and a key added
  with ``+`` anywhere else (``+n_dip=40`` for ``n_dips=40``);
* options the chosen source or planner ignores (:data:`IGNORED`, by the class the group instantiates),
  e.g. ``n_dips`` or ``planner=adaptive`` with ``source=recorded``.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterator, Sequence
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from dipnet.core.keywords import accepted_keywords
from dipnet.planning.plans import AdaptivePlan
from dipnet.preprocessing.sources import RecordedSource
from dipnet.simulator.physics import check_snr_db

#: Hydra's own keys of a ``_target_`` node (not arguments of the target).
HYDRA_KEYS = frozenset({"_target_", "_partial_", "_args_", "_recursive_", "_convert_"})
#: Mesh formats of ``output.mesh_formats`` (:func:`dipnet.outputs.export.save_mesh`).
MESH_FORMATS = ("ply", "stl", "obj")
#: Options (or config groups) a source or planner does not read: ``(group, class it instantiates, its
#: command-line choice, ignored options, why)``.
IGNORED: tuple[tuple[str, type, str, tuple[str, ...], str], ...] = (
    ("source", RecordedSource, "source=recorded", ("n_dips", "orientations", "snr_db", "shape", "reach"),
     "the recording fixes the dips, their directions, their noise and the object"),
    ("planner", AdaptivePlan, "planner=adaptive", ("n_dips", "orientations"),
     "the planner chooses the dips: set planner.budget"),
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
    from hydra._internal.utils import _locate

    for path, node in _target_nodes(cfg):
        target = _locate(str(node._get_node("_target_")._value()))
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
    outside a ``_target_`` node, an option the chosen source or planner ignores (:data:`IGNORED`),
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
    for group, cls, choice, ignored, why in IGNORED:
        if not instantiates(cfg, group, cls):
            continue
        for o in parsed:
            if o.key_or_group.split(".")[0] in ignored and not o.is_delete():
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


def check_grid_options(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for a bad ``ndim``, ``resolution``, ``n_dips``, ``n_slabs``,
    ``fill`` or ``extent_mm``."""
    if cfg.get("ndim") not in (2, 3):
        raise ConfigError(f"ndim must be 2 or 3, got {cfg.get('ndim')!r}")
    _integer(cfg, "resolution", 4, meaning=" (voxels per axis)")
    _integer(cfg, "n_dips", 1)
    _integer(cfg, "n_slabs", 2, nullable=True)
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


def check_values(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` for an option of :file:`conf/config.yaml` out of its range."""
    check_grid_options(cfg)
    check_thresholds(cfg)
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
    formats = cfg.output.get("mesh_formats")
    if not isinstance(formats, ListConfig) or any(f not in MESH_FORMATS for f in formats):
        raise ConfigError(f"output.mesh_formats must be a list of {', '.join(MESH_FORMATS)}, got "
                          f"{OmegaConf.to_container(formats) if isinstance(formats, ListConfig) else formats!r}")
    _integer(cfg, "output.truth_supersample", 1)
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
