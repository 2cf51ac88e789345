"""``botorl bench``: botorl's update speed, FLOP counts, the online loop, and what a paper run
costs (``--paper``); benchmarks/against_d3rlpy.py times the same updates against d3rlpy's.
"""
