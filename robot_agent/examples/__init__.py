"""Example robot backends (see robot_agent/backend.py)."""
