"""Speed benchmarks: botorl's updates against d3rlpy's, FLOP counts, the online loop.

``python -m botorl.benchmarks --against d3rlpy`` (or ``botorl bench --against d3rlpy``).
"""
