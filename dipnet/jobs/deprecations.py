"""Old config spellings, still read: each is rewritten to its new spelling with a warning naming it.

:func:`upgrade_config` runs first in every job (:func:`dipnet.jobs.pipeline.run`), so the code below it
reads one spelling only. Every rewrite warns once per job (``DeprecationWarning`` subclass
:class:`ConfigDeprecation`, also logged).
"""

from __future__ import annotations

import copy
import logging

from omegaconf import DictConfig, OmegaConf, open_dict

from dipnet.core.warn import log_and_warn

log = logging.getLogger(__name__)


class ConfigDeprecation(DeprecationWarning):
    """A config key or value spelled the old way (the message names the new spelling)."""


def deprecated(old: str, new: str) -> None:
    """Warn (and log) that config spelling ``old`` is deprecated in favour of ``new``."""
    message = f"{old} is deprecated: use {new}"
    log_and_warn(log, message, ConfigDeprecation, stacklevel=3)


def _move(cfg: DictConfig, old: str, new: str) -> None:
    """Move the value of dotted key ``old`` to ``new`` (replacing it) with a warning when it is given
    (not null); the old key is removed either way, so nothing below reads it."""
    parent_key, _, leaf = old.rpartition(".")
    parent = OmegaConf.select(cfg, parent_key)
    if not isinstance(parent, DictConfig) or leaf not in parent:
        return
    value = parent[leaf]
    with open_dict(cfg):
        if value is not None:
            shown = value
            if isinstance(value, DictConfig):  # as typed on the command line: {n_fold: 3, mirror: true}
                shown = "{" + ", ".join(f"{k}: {v}"
                                        for k, v in OmegaConf.to_container(value, resolve=True).items()) + "}"
            deprecated(old, f"{new}={shown}")
            OmegaConf.update(cfg, new, value, force_add=True)
        del parent[leaf]


def upgrade_config(cfg: DictConfig) -> DictConfig:
    """A copy of a reconstruct config with every deprecated spelling rewritten to the new one:
    ``source.reader.symmetry`` -> ``symmetry`` (top level: every source's measurement is symmetrised once)."""
    cfg = copy.deepcopy(cfg)
    _move(cfg, "source.reader.symmetry", "symmetry")
    return cfg


def upgrade_scan_config(cfg: DictConfig) -> DictConfig:
    """:func:`upgrade_config` for a scan config (``conf/scan.yaml``): ``rig.geometry.origin_height_mm`` ->
    ``rig.origin_height_mm`` (the geometry node is a :class:`~dipnet.core.geometry.RigGeometry`), and an
    ``orientations`` node ``{kind, n, seed, tilts, spins, max_tilt_deg}`` (the old spelling) ->
    ``orientations=<kind>`` with top-level ``n_dips``, ``seed``, ``tilts``, ``spins``, ``max_tilt_deg`` (one
    meaning of ``orientations``: the set's name, as in ``conf/config.yaml``)."""
    cfg = copy.deepcopy(cfg)
    _move(cfg, "rig.geometry.origin_height_mm", "rig.origin_height_mm")
    if isinstance(cfg.get("orientations"), DictConfig):
        node = OmegaConf.to_container(cfg.orientations, resolve=True)
        with open_dict(cfg):
            cfg.orientations = node.pop("kind", "fibonacci")
            deprecated("orientations.kind", f"orientations={cfg.orientations}")
            for old, new in (("n", "n_dips"), ("seed", "seed"), ("tilts", "tilts"), ("spins", "spins"),
                             ("max_tilt_deg", "max_tilt_deg")):
                if node.get(old) is not None:
                    deprecated(f"orientations.{old}", f"{new}={node[old]}")
                    OmegaConf.update(cfg, new, node[old], force_add=True)
    return cfg
