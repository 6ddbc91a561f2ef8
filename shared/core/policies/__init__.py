"""Policies shipped with the project: ``general/``, the general policy (shared/core/graph_policy.py)."""
