"""The central training server: episodes, EM, CE-PG, versioned policies (issue 4)."""
