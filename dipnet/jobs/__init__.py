"""The only code that reads a config: the reconstruct and calibrate jobs, option checks, runtime
(user errors, threads, memory checks, run locks).
"""
