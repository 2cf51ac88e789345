"""Experiments at scale: `botorl sweep` (grids of runs on one machine or a Ray cluster) and
`botorl report` (Table 1, Figure 5 and the alpha-sensitivity figure of the paper).

- `grid`: the grid and each trial's run-directory name and `botorl run` arguments;
- `runner`: launching, resuming and retrying trials (sequential / local / ray backends);
- `report`: reading finished runs, the statistics and the figures;
- `cli`: the two commands.
"""
