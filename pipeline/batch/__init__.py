"""Many captures at once on Ray: ``python -m pipeline batch``."""
