"""Numbers about a result: metrics, consistency, uncertainty, resolvability. Writes no files.
"""
