"""Alembic migrations of the server's database (training_server.store.migrate runs them at start)."""
