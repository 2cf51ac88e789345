"""Run configurations: the dataclasses (``schema``), per-task presets (``presets``), and
``resolve`` / ``validate`` (``resolve``)."""
