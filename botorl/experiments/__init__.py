"""Experiments at scale: `botorl sweep` (grids of runs on one machine or a Ray cluster) and
`botorl report` (the paper's tables and figures); the modules: docs/architecture.md."""
