"""Learned priors: training pairs from generated shapes, the 3D denoiser network, its weights
files and the training loop (``scripts/train_prior.py``). The prior that solvers use is
:class:`dipnet.solvers.learned.LearnedPrior`."""
