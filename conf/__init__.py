"""dipnet's Hydra configuration tree (shipped as the package ``dipnet.conf``)."""
