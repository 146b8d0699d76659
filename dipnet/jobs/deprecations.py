"""Old config spellings, still read: each is rewritten to its new spelling with a warning naming it.

:func:`upgrade_config` runs first in every job (:func:`dipnet.jobs.pipeline.run`), so the code below it
reads one spelling only. Every rewrite warns once per job (``DeprecationWarning`` subclass
:class:`ConfigDeprecation`, also logged).
"""

from __future__ import annotations

import copy
import logging
import warnings

from omegaconf import DictConfig, OmegaConf, open_dict

log = logging.getLogger(__name__)


class ConfigDeprecation(DeprecationWarning):
    """A config key or value spelled the old way (the message names the new spelling)."""


def deprecated(old: str, new: str) -> None:
    """Warn (and log) that config spelling ``old`` is deprecated in favour of ``new``."""
    message = f"{old} is deprecated: use {new}"
    log.warning(message)
    warnings.warn(message, ConfigDeprecation, stacklevel=3)


def _move_reader_symmetry(cfg: DictConfig) -> None:
    """``source.reader.symmetry`` -> the top-level ``symmetry`` (applied once, to every source)."""
    reader = OmegaConf.select(cfg, "source.reader")
    if not isinstance(reader, DictConfig) or reader.get("symmetry") is None:
        return
    spec = reader.symmetry
    deprecated("source.reader.symmetry", f"symmetry={OmegaConf.to_yaml(spec, resolve=True).strip() or '{}'} "
               "(top level: every source's measurement is symmetrised once)")
    with open_dict(cfg):
        if not cfg.get("symmetry"):
            cfg.symmetry = spec
        del reader["symmetry"]


def upgrade_config(cfg: DictConfig) -> DictConfig:
    """A copy of ``cfg`` with every deprecated spelling rewritten to the new one (module docstring)."""
    cfg = copy.deepcopy(cfg)
    for step in (_move_reader_symmetry,):
        step(cfg)
    return cfg


def _move_origin_height(cfg: DictConfig) -> None:
    """``rig.geometry.origin_height_mm`` -> ``rig.origin_height_mm`` (the geometry node is a RigGeometry)."""
    geometry = OmegaConf.select(cfg, "rig.geometry")
    if not isinstance(geometry, DictConfig) or "origin_height_mm" not in geometry:
        return
    value = geometry.origin_height_mm
    with open_dict(cfg):
        if value is not None:
            deprecated("rig.geometry.origin_height_mm", f"rig.origin_height_mm={value}")
            cfg.rig.origin_height_mm = value
        del geometry["origin_height_mm"]


def upgrade_scan_config(cfg: DictConfig) -> DictConfig:
    """:func:`upgrade_config` for a scan config (``conf/scan.yaml``)."""
    cfg = copy.deepcopy(cfg)
    for step in (_move_origin_height,):
        step(cfg)
    return cfg
