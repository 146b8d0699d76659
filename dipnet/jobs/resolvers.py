"""The config resolvers dipnet's Hydra configs use, registered on import (``import dipnet`` does it).

* ``${dipnet_data:relative/path}``: the absolute path of a file in the bundled data folder
  (:func:`dipnet.preprocessing.datasets.data_path`), e.g. ``${dipnet_data:meshes/bunny.ply}``.
"""

from __future__ import annotations

from omegaconf import OmegaConf

from dipnet.preprocessing.datasets import data_path

OmegaConf.register_new_resolver("dipnet_data", lambda relative="": str(data_path(relative)), replace=True)
