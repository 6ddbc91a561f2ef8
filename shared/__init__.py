"""Code shared by the robot agent and the training server: maps, models, beliefs, simulator."""
