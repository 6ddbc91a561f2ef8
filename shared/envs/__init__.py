"""MuRES as environments for multi-agent RL libraries: ``mures_v0`` (PettingZoo and TorchRL)."""
