"""Which dips to take: the next-best-dip planner and the adaptive loop.
"""
