"""The offline-to-online pipeline: what ``botorl run`` / ``resume`` / ``eval`` / ``export`` do
(docs/running.md; the modules: docs/architecture.md).
"""
