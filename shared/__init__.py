"""The MuRES fleet library, in rooms by who uses them (docs/architecture.md): core (agent and
server, numpy only), engine, learning, planners, the searcher registry, and the CLI's tools."""

__version__ = "0.1.0"
