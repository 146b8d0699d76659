"""Experiments at scale: collect the jobs of Hydra sweeps, aggregate, tabulate and plot them.

A sweep directory (``python scripts/reconstruct.py -m ...``) holds one directory per job; each
finished job wrote the files of :mod:`dipnet.jobs.pipeline` (``.hydra/config.yaml``,
``metrics.json``, ``reconstruction.npz``, ...). A job that raised wrote ``error.txt`` instead
of ``metrics.json`` (see :func:`dipnet.jobs.sweep_jobs.guarded_job`); a job with neither is unfinished.

Pipeline (:mod:`~dipnet.experiments.collect`): ``collect_runs`` (directories -> ``Run``) -> ``run_rows``
(flat dicts, one per job) -> ``aggregate`` (mean and spread per solver x n_dips x snr_db) -> tables
(:mod:`~dipnet.experiments.tables`) and figures (:mod:`~dipnet.experiments.figures`).
:class:`dipnet.jobs.sweep_jobs.JobLogCallback` logs one line per finished job and lists the failures
at the end of a sweep.

The benchmark scripts' shared parts live here too: their ``--quick`` mode (:mod:`~dipnet.experiments.quick_mode`),
the calibration benchmarks' random rigs and reference balls (:mod:`~dipnet.experiments.random_rigs`) and the learned
prior's training pairs and training (:mod:`~dipnet.experiments.prior_pairs`, :mod:`~dipnet.experiments.prior_training`).
"""
