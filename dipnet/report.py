"""``python -m dipnet.report JOB_DIR [JOB_DIR ...]``: each run's ``report.html`` (:mod:`dipnet.experiments.report`)."""

from dipnet.experiments.report import main

if __name__ == "__main__":
    raise SystemExit(main())
