"""Code shared by the robot agent and the training server: maps, models, beliefs, simulator."""

__version__ = "0.1.0"
